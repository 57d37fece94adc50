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
