"""The README's main job, through the CLI runner: every output appears."""

from __future__ import annotations

import json

from mems_stereo.cli import main


# one pytest-xdist worker runs the tests that share the bundled samples' calibrations and
# the imperfect-hardware comparison (tests/conftest.py: ``shared_results``, XDIST_GROUPS)
def test_demo_writes_every_output(tmp_path, capsys, monkeypatch, shared_results):
    """Runs ``mems-stereo demo --help``'s example as it stands, from an empty folder.

    Its calibrations of the bundled walls are those of tests/test_cli_outputs.py's
    ``ctx`` and its imperfect-hardware step is tests/test_demo_hardware.py's
    ``comparison`` (same calls, computed once: ``shared_results``)."""
    import shlex

    from mems_stereo.cli import demo

    monkeypatch.chdir(tmp_path)
    argv = shlex.split(demo.EXAMPLE)
    assert argv[:2] == ["mems-stereo", "demo"]
    assert main(argv[1:]) == 0
    out = tmp_path / argv[argv.index("-o") + 1]
    text = capsys.readouterr().out
    summary = json.loads((out / "demo_summary.json").read_text())
    names = {p.split("/")[-1] for p in summary["outputs"]}
    for name in ("fig2_acquisition.png", "calibrated_system.json", "calibration_report.pdf",
                 "room.ply", "room.las",
                 "floodlight.ply", "fig8_room_histograms.png",
                 "fig9_floodlight_histograms.png", "fig5_uncertainty.png", "room_render.png"):
        assert name in names
    for p in summary["outputs"]:
        assert (out / p.split("/")[-1]).stat().st_size > 0
    assert "signal recall" in text and "raw counts 19518" in text
    assert "not observable from these data: baseline_y" in text
    # one sample story: the calibrated system beats the nominal one on both scenes
    verdicts = summary["calibration_gain_verdicts"]
    assert set(verdicts) == {"room", "floodlight"}
    for scene, v in verdicts.items():
        assert v == {"median_error": True, "coverage": True, "recall": True}, scene
    rows = {(r["scene"], r["system"]): r for r in summary["calibration_gain"]}
    for scene in verdicts:
        n, c = rows[scene, "nominal"], rows[scene, "calibrated"]
        assert c["median_error"] < n["median_error"] and c["coverage"] > n["coverage"]
        assert c["recall"] >= n["recall"]
    assert "median point error" in text
    # the same story for the Lissajous scanner: its walls calibrate the system that recorded
    # lissajous64.h5, which then beats the nominal one (scored against the sample's truth)
    assert summary["two_axis_calibration_gain_verdicts"] == {
        "lissajous64": {"median_error": True, "coverage": True, "recall": True}}
    rows2 = {r["system"]: r for r in summary["two_axis_calibration_gain"]}
    n, c = rows2["nominal"], rows2["calibrated"]
    assert c["median_error"] < n["median_error"] and c["coverage"] > n["coverage"]
    assert c["recall"] >= n["recall"]
    assert n["illuminated"] == c["illuminated"]  # one truth, two systems
    assert "lissajous64: calibrated better on median point error: yes" in text
    # the cloud written is the calibrated one that was scored
    ply = (out / "lissajous64.ply").read_bytes()
    assert f"element vertex {c['points']}\n".encode() in ply[:2000]
    assert "lissajous64_calibrated_system.json" in names
