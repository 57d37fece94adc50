"""``mems-stereo calibrate``: argument checks (the full run is benchmarks/bench_calibrate.py)."""

from __future__ import annotations

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
