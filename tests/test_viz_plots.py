"""Figures (matplotlib, Agg) and the histogram file format."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mems_stereo.viz import plots

from mems_stereo.errors import FormatError
from mems_stereo.io.histograms import read_histograms, write_histograms
from mems_stereo.pipeline.cloud import PointCloud


def _png(path):
    img = cv2.imread(str(path))
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 5  # not a blank canvas
    assert sorted(p.name for p in path.parent.iterdir() if p.name.startswith(".")) == []
    return img


def _hist(rng, w=24, nb=300):
    sig = np.zeros((w, nb), np.int64)
    sig[:, 100:103] = rng.poisson(5, (w, 3))
    noise = rng.poisson(0.1, (w, nb))
    return sig + noise, sig, noise


def test_plot_acquisition(tmp_path):
    from mems_stereo import acquisition_statistics, preset

    st = acquisition_statistics(preset("burkard2022"), 400, 2.5, frequency_ratio=0.0785)
    _png(plots.plot_acquisition(st, tmp_path / "fig2.png", title="400 shots"))


def test_plot_histograms(tmp_path):
    raw, sig, noise = _hist(np.random.default_rng(0))
    a = _png(plots.plot_histograms(raw, sig, noise, tmp_path / "h.png", max_code=256))
    b = _png(plots.plot_histograms(raw[None], sig[None], noise[None], tmp_path / "h3.png",
                                   max_code=256, row=0, log=False))
    assert a.shape == b.shape
    with pytest.raises(FormatError, match="one shape"):
        plots.plot_histograms(raw, sig[:, :10], noise, tmp_path / "x.png")
    with pytest.raises(FormatError, match="max_code"):
        plots.plot_histograms(raw, sig, noise, tmp_path / "x.png", max_code=0)
    with pytest.raises(FormatError, match="row"):
        plots.plot_histograms(raw[None], sig[None], noise[None], tmp_path / "x.png", row=3)
    with pytest.raises(FormatError, match=".jpg"):
        plots.plot_histograms(raw, sig, noise, tmp_path / "x.jpg")


def test_plot_peaks(tmp_path):
    raw, sig, noise = _hist(np.random.default_rng(1))
    filt = cv2.GaussianBlur(sig.astype(np.float64), (5, 1), 1.0)
    mask = np.zeros(sig.shape, bool)
    mask[:, 101] = True
    _png(plots.plot_peaks(filt, np.full(sig.shape[0], 1.0), mask, tmp_path / "p.png",
                          max_code=256))
    _png(plots.plot_peaks(filt, 1.0, np.argwhere(mask), tmp_path / "p2.png"))
    with pytest.raises(FormatError, match="threshold"):
        plots.plot_peaks(filt, np.ones(5), mask, tmp_path / "x.png")


def test_ellipse_params_against_rotation():
    a, b, ang = 0.03, 0.01, np.radians(30)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    cov = R @ np.diag([a**2, b**2]) @ R.T
    w, h, deg = plots.ellipse_params(cov, n_sigma=2)
    np.testing.assert_allclose([w, h], [4 * a, 4 * b])
    assert np.isclose(deg % 180, 30)


def test_one_sigma_ellipse_holds_39_percent_of_samples():
    # an independent check: P(Mahalanobis distance <= 1) = 1 - exp(-1/2) in 2-D
    rng = np.random.default_rng(2)
    cov = np.array([[4e-4, 1.5e-4], [1.5e-4, 1e-4]])
    s = rng.multivariate_normal([0, 0], cov, 200000)
    w, h, deg = plots.ellipse_params(cov)
    t = np.radians(deg)
    u = s @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])  # into ellipse axes
    inside = (u[:, 0] / (w / 2)) ** 2 + (u[:, 1] / (h / 2)) ** 2 <= 1
    assert abs(inside.mean() - (1 - np.exp(-0.5))) < 0.005


def test_plot_uncertainty_bounds(tmp_path):
    rng = np.random.default_rng(3)
    mu = np.array([[0.0, 2.0], [0.4, 3.0], [-0.4, 4.0]])
    cov = np.array([np.diag([1e-4, 9e-4]) * (i + 1) for i in range(3)])
    s = rng.multivariate_normal(mu[0], cov[0], 300)
    _png(plots.plot_uncertainty_bounds(mu, cov, tmp_path / "u.png", n_sigma=(1, 2, 3),
                                       samples=s, labels=["a", "b", "c"], scale=5))
    with pytest.raises(FormatError, match="covariances"):
        plots.plot_uncertainty_bounds(mu, cov[:2], tmp_path / "x.png")


def test_plot_calibration_residuals(tmp_path):
    rng = np.random.default_rng(4)
    _png(plots.plot_calibration_residuals({"pixel": rng.normal(size=80),
                                           "range": rng.normal(size=(30, 2))},
                                          tmp_path / "r.png", unit="px"))
    _png(plots.plot_calibration_residuals(rng.normal(size=10), tmp_path / "r1.png"))
    with pytest.raises(FormatError, match="residuals"):
        plots.plot_calibration_residuals({}, tmp_path / "x.png")


def test_plot_cloud_topview(tmp_path):
    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-1, 1, 500), np.zeros(500), rng.uniform(1, 4, 500)]
    c = PointCloud(pts, {"range": np.linalg.norm(pts, axis=1)})
    _png(plots.plot_cloud_topview(c, tmp_path / "t.png"))
    with pytest.raises(FormatError, match="counts"):
        plots.plot_cloud_topview(c, tmp_path / "x.png", color_by="counts")


def test_histogram_file_round_trip(tmp_path):
    raw, sig, noise = _hist(np.random.default_rng(6))
    p = write_histograms(tmp_path / "h.h5", raw[None], sig[None], noise[None],
                         {"bin_width": 312.5e-12, "source": "room.h5"})
    h = read_histograms(p)
    r, s, n, attrs = h.raw, h.signal, h.noise, h.attrs
    for got, ref in ((r, raw), (s, sig), (n, noise)):
        assert got.dtype == np.int32 and got.shape == (1,) + ref.shape
        np.testing.assert_array_equal(got[0], ref)
    assert attrs == {"bin_width": 312.5e-12, "source": "room.h5"}
    r2 = read_histograms(write_histograms(tmp_path / "h2.h5", raw, sig, noise)).raw
    np.testing.assert_array_equal(r2, r)  # (W, n_bins) is stored as (1, W, n_bins)


def test_histogram_file_errors(tmp_path):
    import h5py

    raw, sig, noise = _hist(np.random.default_rng(7), w=4, nb=120)
    with pytest.raises(FormatError, match="one shape"):
        write_histograms(tmp_path / "x.h5", raw, sig[:2], noise)
    with pytest.raises(FormatError, match="/noise"):
        write_histograms(tmp_path / "x.h5", raw, sig, -noise - 1)
    with pytest.raises(FormatError, match="integer"):
        write_histograms(tmp_path / "x.h5", raw, sig, noise * 0.5)
    assert not (tmp_path / "x.h5").exists()
    with pytest.raises(FileNotFoundError):
        read_histograms(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("no")
    with pytest.raises(FormatError, match="HDF5"):
        read_histograms(tmp_path / "text.h5")
    p = write_histograms(tmp_path / "ok.h5", raw, sig, noise)
    with h5py.File(p, "a") as f:
        del f["signal"]
    with pytest.raises(FormatError, match="/signal"):
        read_histograms(p)
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "mems-stereo/recording"
    with pytest.raises(FormatError, match="format"):
        read_histograms(tmp_path / "other.h5")
