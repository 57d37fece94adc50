"""Two-axis recordings, simulator and pipeline, end to end (small, seeded)."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from mems_stereo.cli import main
from mems_stereo.errors import FormatError
from mems_stereo.geometry.gating import GateSpec
from mems_stereo.io.recording import read_recording
from mems_stereo.io.recording2d import (
    is_two_axis_recording,
    read_recording_2d,
    write_recording_2d,
)
from mems_stereo.model.camera import pixels_to_rays
from mems_stereo.model.presets import lissajous64, raster128x96
from mems_stereo.pipeline.twoaxis import process_recording_2d
from mems_stereo.sim.scene import load_scene
from mems_stereo.sim.simulate2d import simulate_2d

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "samples" / "twoaxis_scene.json"


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


@pytest.fixture(scope="module")
def small(scene):
    return simulate_2d(lissajous64(), scene, 12000, rng=np.random.default_rng(7))


def test_recording_round_trip_and_one_axis_reader_refuses(small, tmp_path):
    p = write_recording_2d(tmp_path / "r.h5", small)
    assert is_two_axis_recording(p)
    r = read_recording_2d(p)
    for a in ("shot_time", "zero_crossings", "event_shot", "event_pixel", "event_code",
              "read_count"):
        np.testing.assert_array_equal(getattr(r, a), getattr(small, a))
    np.testing.assert_array_equal(r.monitor2.zero_crossings, small.monitor2.zero_crossings)
    np.testing.assert_array_equal(r.truth["label"], small.truth["label"])
    assert r.readout == small.readout
    with pytest.raises(FormatError, match="scan_axes"):
        read_recording(p)
    assert not is_two_axis_recording(ROOT / "samples" / "room.h5")
    with h5py.File(p, "r+") as f:  # a code above n_bins is refused on read
        f["events/code"][0] = 5000
    with pytest.raises(FormatError, match="/events/code"):
        read_recording_2d(p)


def test_simulator_is_deterministic_and_gate_keeps_returns(scene, small):
    again = simulate_2d(lissajous64(), scene, 12000, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(again.event_code, small.event_code)
    np.testing.assert_array_equal(again.event_pixel, small.event_pixel)
    t = small.truth
    assert t["signal_total"] > 2000
    assert t["signal_lost"] <= 0.01 * t["signal_total"]
    assert small.read_count.mean() / 4096 < 0.05
    # events only on read slots, sorted, one per slot
    key = small.event_shot * 4096 + small.event_pixel
    assert np.all(np.diff(key) > 0)


def test_a_too_narrow_gate_loses_returns(scene):
    rec = simulate_2d(lissajous64(), scene, 3000, rng=np.random.default_rng(8),
                      gate=GateSpec(0.5, 1.0, 0.6))  # working range misses the scene
    assert rec.truth["signal_lost"] > 0.9 * rec.truth["signal_total"]


def test_pipeline_recall_accuracy_and_honest_sigma(scene, small):
    res = process_recording_2d(small)
    assert res.truth["recall"] >= 0.98
    assert res.truth["noise_rejection"] > 0.9
    c = res.cloud
    assert len(c) > 500 and not c.missing_required()
    s = small.system
    uv = np.stack([c["pixel"], c["row"]], 1).astype(float)
    hits = scene.cast(np.zeros(3), pixels_to_rays(uv, s.receiver.camera_matrix))
    err = np.linalg.norm(c.points - hits.point, axis=1)
    near = np.linalg.norm(hits.point, axis=1) < 6.0
    assert np.median(err[near]) < 0.03
    # error along the pixel ray against the propagated σ of the range
    r_err = np.linalg.norm(c.points, axis=1) - np.linalg.norm(hits.point, axis=1)
    pull = r_err[near] / c["sigma_r"][near]
    assert 0.4 < np.median(np.abs(pull)) < 1.3


def test_full_readout_labels_agree_with_gated(scene):
    s = lissajous64()
    kw = dict(rng=np.random.default_rng(9), background_hz=2e5)
    full = simulate_2d(s, scene, 1500, gate=None, **kw)
    assert full.readout["mode"] == "full" and np.all(full.read_count == 4096)
    res = process_recording_2d(full)
    assert res.truth["recall"] >= 0.98
    assert res.counts["read_fraction"] == 1.0


def test_raster_system_runs(scene):
    rec = simulate_2d(raster128x96(), scene, 8000, rng=np.random.default_rng(10))
    res = process_recording_2d(rec)
    assert res.truth["recall"] >= 0.98 and len(res.cloud) > 100


def test_cli_simulate_process_export(tmp_path, capsys):
    rec = tmp_path / "l.h5"
    assert main(["simulate", str(SCENE), "--system", "lissajous64", "--shots", "6000",
                 "--seed", "3", "-o", str(rec)]) == 0
    assert is_two_axis_recording(rec)
    ply = tmp_path / "l.ply"
    assert main(["process", str(rec), "-o", str(ply), "--labels", str(tmp_path / "lab.h5")]) == 0
    out = capsys.readouterr().out
    assert "two-axis" in out and "signal recall" in out
    assert main(["export", str(ply), "-o", str(tmp_path / "l.pcd")]) == 0
    assert (tmp_path / "l.pcd").stat().st_size > 0
