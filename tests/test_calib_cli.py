"""``mems-stereo calibrate``: argument checks (the full run is benchmarks/bench_calibrate.py)."""

from __future__ import annotations

import pytest

from mems_stereo.cli import main


def test_target_distance_count_must_match(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "b.h5", "-o", str(tmp_path / "s.json"),
               "--target-distance", "1.0"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--target-distance" in err and "one distance per recording (2)" in err
    assert not (tmp_path / "s.json").exists()


def test_missing_recording_is_reported(tmp_path, capsys):
    rc = main(["calibrate", str(tmp_path / "nope.h5"), "-o", str(tmp_path / "s.json")])
    assert rc == 2
    assert "nope.h5" in capsys.readouterr().err


def test_distances_file_errors_name_the_file(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"),
               "--target-distances-file", str(tmp_path / "none.json")])
    assert rc == 2
    assert "none.json" in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_distance_inputs_are_exclusive(tmp_path):
    with pytest.raises(SystemExit) as e:
        main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"), "--target-distance", "1.0",
              "--target-distances-file", "d.json"])
    assert e.value.code == 2


def test_distance_std_must_be_positive(tmp_path, capsys):
    rc = main(["calibrate", "a.h5", "-o", str(tmp_path / "s.json"), "--target-distance", "1.0",
               "--distance-std", "0"])
    assert rc == 2
    assert "--distance-std" in capsys.readouterr().err


SAMPLES = __import__("pathlib").Path(__file__).resolve().parents[1] / "samples"


def test_recordings_that_are_not_flat_walls_fail_cleanly(tmp_path, capsys):
    """The room and floodlight recordings are no calibration walls: exit 1,
    one line saying why, no system file; the report says why too."""
    out, rep = tmp_path / "s.json", tmp_path / "r.json"
    rc = main(["calibrate", str(SAMPLES / "room.h5"), str(SAMPLES / "floodlight.h5"),
               "-o", str(out), "--report", str(rep)])
    err = capsys.readouterr().err
    assert rc in (1, 2)
    assert "calibration failed" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    import json

    doc = json.loads(rep.read_text())
    assert doc["ok"] is False and doc["reason"] in err


def test_failed_calibration_writes_the_pdf_report(tmp_path, capsys):
    """--report X.pdf on a failure: exit non-zero, no system file, a 2-page PDF saying why."""
    import re

    out, rep = tmp_path / "s.json", tmp_path / "r.pdf"
    rc = main(["calibrate", str(SAMPLES / "room.h5"), str(SAMPLES / "floodlight.h5"),
               "-o", str(out), "--report", str(rep)])
    assert rc in (1, 2) and not out.exists()
    assert "calibration failed" in capsys.readouterr().err
    data = rep.read_bytes()
    assert data.startswith(b"%PDF") and b"(FAILED)" in data
    assert len(re.findall(rb"/Type\s*/Page[^s]", data)) == 2


def test_contradicting_distance_named_no_file(tmp_path, capsys):
    out = tmp_path / "s.json"
    walls = [str(SAMPLES / f"calib_{d}m.h5") for d in ("1.5", "2.5", "4.0")]
    rc = main(["calibrate", *walls, "-o", str(out), "--target-distance", "1.494", "2.307",
               "3.992", "--distance-std", "0.002"])
    cap = capsys.readouterr()
    assert rc == 1 and not out.exists()
    assert "measured distance of wall 1" in cap.err and "calib_2.5m.h5" in cap.err
    assert "warning: the measured distance of wall 1" in cap.out
