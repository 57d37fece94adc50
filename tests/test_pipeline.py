"""The processing chain: streaming equals whole-file, paper pattern, truth scores, bad input."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mems_stereo.cli import main
from mems_stereo.errors import FormatError
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


@pytest.fixture(scope="module")
def room():
    return process_recording(SAMPLES / "room.h5")


def test_streaming_in_chunks_equals_whole_file(room):
    small = process_recording(SAMPLES / "room.h5", settings=Settings(chunk_shots=97))
    for k in room.histograms:
        np.testing.assert_array_equal(room.histograms[k], small.histograms[k])
    np.testing.assert_array_equal(room.cloud.points, small.cloud.points)
    for k in room.cloud.attributes:
        np.testing.assert_array_equal(room.cloud[k], small.cloud[k])
    assert room.counts == small.counts


def test_room_light_shows_the_papers_pattern(room):
    """Signal counts close to the number of shots, raw counts several times larger."""
    c = room.counts
    assert 0.8 * c["shots"] < c["signal"] < 2.0 * c["shots"]
    assert c["raw"] > 5 * c["signal"]
    assert room.truth["recall"] >= 0.98
    assert room.truth["noise_rejection"] >= 0.97


def test_peak_pixels_unchanged_by_classification(room):
    """Where a pixel's raw histogram has a clear return, the signal peak is at the same code."""
    raw = room.histograms["raw"][0].astype(float)
    sig = room.histograms["signal"][0].astype(float)
    from mems_stereo.pipeline.histograms import moving_average

    w = 49
    raw_s, sig_s = moving_average(raw, w), moving_average(sig, w)
    strong = sig_s.max(axis=1) * w >= 8
    assert strong.sum() >= 5
    agree = np.abs(raw_s[strong].argmax(1) - sig_s[strong].argmax(1)) <= w // 2
    assert agree.mean() >= 0.9


def test_background_estimate_recovers_the_simulated_rate(room):
    bg = room.background_hz[np.isfinite(room.background_hz)]
    # 100 kHz ambient + 1 kHz dark counts, per pixel
    assert np.median(bg) == pytest.approx(101e3, rel=0.05)


def test_process_command_writes_cloud_labels_histograms(tmp_path, capsys):
    out = tmp_path / "room.ply"
    lab = tmp_path / "labels.h5"
    hist = tmp_path / "hist.h5"
    assert main(["process", str(SAMPLES / "room.h5"), "-o", str(out), "--labels", str(lab),
                 "--histograms", str(hist), "--system",
                 str(SAMPLES / "calib_true_system.json")]) == 0
    text = capsys.readouterr().out
    assert "raw counts 19518" in text and "signal recall" in text
    from mems_stereo.viz.export import read_cloud

    cloud = read_cloud(out)
    for name in ("counts", "pixel", "range", "sigma_r", "sigma_phi"):
        assert name in cloud.attributes
    with h5py.File(lab) as f:
        assert f["label"].shape == (800, 1, 192) and f["theta"].shape == (800,)
        n_signal = int((f["label"][()] == 1).sum())
    assert f"classified signal {n_signal}" in text


def _corrupt(src, dst, what, value=None):
    import shutil

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        if what == "codes":
            b = f["shots/bins"][()]
            b[value % b.shape[0], 0, value % 192] = 5000
            del f["shots/bins"]
            f["shots/bins"] = b
        elif what == "time":
            t = f["shots/time"][()]
            i = 1 + value % (t.size - 1)
            t[i] = t[i - 1]
            del f["shots/time"]
            f["shots/time"] = t
        elif what == "dtype":
            b = f["shots/bins"][()].astype(np.int32)
            del f["shots/bins"]
            f["shots/bins"] = b
        elif what == "crossings":
            del f["scanner/zero_crossings"]
            f["scanner/zero_crossings"] = np.array([0.0])
            del f["scanner/rising"]
            f["scanner/rising"] = np.array([0], np.uint8)
        elif what == "system":
            del f["system"]
            f["system"] = '{"format": "mems-stereo/system", "version": 1, "receiver": {}}'


@settings(max_examples=10, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(["codes", "time", "dtype", "crossings", "system"]), st.integers(0, 10**6))
def test_bad_recordings_leave_no_output(tmp_path_factory, what, seed):
    d = tmp_path_factory.mktemp("bad")
    bad = d / "bad.h5"
    _corrupt(SAMPLES / "room.h5", bad, what, seed)
    with pytest.raises(FormatError) as e:
        process_recording(bad, labels_path=d / "labels.h5")
    assert str(bad) in str(e.value)
    assert sorted(p.name for p in d.iterdir()) == ["bad.h5"]
    assert main(["process", str(bad), "-o", str(d / "c.ply"), "--labels",
                 str(d / "l.h5")]) == 2
    assert sorted(p.name for p in d.iterdir()) == ["bad.h5"]


def test_poisson_quantile_equals_scipy_stats():
    from scipy.stats import poisson

    from mems_stereo.physics.background import poisson_isf

    mu = np.array([1e-9, 0.01, 0.5, 3.0, 47.0, 900.0, 2.5e4])
    for alpha in (1e-6, 1e-3, 0.05, 0.5):
        np.testing.assert_array_equal(poisson_isf(alpha, mu), poisson.isf(alpha, mu))
