"""Temporal fusion (mems_stereo.pipeline.temporal): accumulate while a pixel agrees with
its history, restart when it does not; checked against independent NumPy sums and the
Gaussian tail the test is built on."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, chi2, norm

from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.scan_dwell import Systematic
from mems_stereo.pipeline.temporal import TemporalFusion

W = 64


def frame_cloud(r, sigma, t, band=(100, 150), pixels=None, counts=5):
    """A line sensor's frame: one point per pixel on the optical axis of its column."""
    r = np.asarray(r, float)
    n = r.size
    pix = np.arange(n) if pixels is None else np.asarray(pixels)
    sig = np.broadcast_to(np.asarray(sigma, float), (n,)).copy()
    pts = np.stack([0.01 * pix * r, np.zeros(n), r], axis=1)
    return PointCloud(pts, {
        "counts": np.full(n, counts, np.int32), "pixel": pix.astype(np.int32),
        "row": np.zeros(n, np.int32), "range": r, "sigma_r": sig,
        "sigma_phi": 1e-3 * sig, "sigma_x": 0.1 * sig, "sigma_y": 0.0 * sig,
        "sigma_z": sig, "t": np.full(n, float(t)),
        "step_lo": np.full(n, band[0], np.int32), "step_hi": np.full(n, band[1], np.int32)})


def test_static_pixel_is_the_inverse_variance_mean():
    rng = np.random.default_rng(3)
    fus = TemporalFusion(1, W, 0.997)
    sig = rng.uniform(0.01, 0.03, size=(6, W))
    r = 4.0 + 0.2 * sig * rng.standard_normal((6, W))  # well inside the bound
    for i in range(6):
        out = fus.update(frame_cloud(r[i], sig[i], t=0.1 * i))
    w = 1.0 / sig ** 2
    np.testing.assert_allclose(out["range"], (w * r).sum(0) / w.sum(0), rtol=1e-12)
    np.testing.assert_allclose(out["sigma_r"], 1.0 / np.sqrt(w.sum(0)), rtol=1e-12)
    np.testing.assert_allclose(out["sigma_z"], np.sqrt((w ** 2 * sig ** 2).sum(0)) / w.sum(0),
                               rtol=1e-12)
    assert np.all(out["age"] == 6) and np.all(out["counts"] == 30)
    np.testing.assert_allclose(out["t"], 0.25)  # equal counts: the mean of the frames' t
    assert fus.tests == 5 * W and fus.restarts == 0


def test_a_jump_beyond_k_sigma_restarts_and_a_small_one_does_not():
    fus = TemporalFusion(1, W, 0.997)
    for i in range(4):
        fus.update(frame_cloud(np.full(W, 3.0), 0.02, t=i))
    # σ of the difference: sqrt(0.02² + 0.02²/4); k = 2.97 → bound 6.6 cm
    step = np.where(np.arange(W) < W // 2, 0.05, 0.09)
    out = fus.update(frame_cloud(3.0 + step, 0.02, t=4))
    small = np.arange(W) < W // 2
    assert np.all(out["age"][small] == 5) and np.all(out["age"][~small] == 1)
    np.testing.assert_allclose(out["range"][~small], 3.09)
    np.testing.assert_allclose(out["sigma_r"][~small], 0.02)
    np.testing.assert_allclose(out["range"][small], 3.0 + 0.05 / 5)
    assert fus.restarts == W // 2


def test_a_disjoint_scan_angle_band_restarts():
    fus = TemporalFusion(1, W, 0.997)
    fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=0, band=(100, 150)))
    out = fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=1, band=(151, 200)))
    assert np.all(out["age"] == 1)
    out = fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=2, band=(190, 260)))
    assert np.all(out["age"] == 2)


def test_missing_frames_keep_the_history_and_only_observed_pixels_are_returned():
    fus = TemporalFusion(1, W, 0.997)
    fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=0))
    out = fus.update(frame_cloud(np.full(3, 2.0), 0.01, t=1, pixels=[5, 9, 60]))
    assert len(out) == 3 and out["pixel"].tolist() == [5, 9, 60]
    assert out["age"].tolist() == [2, 2, 2]


def test_false_restart_rate_is_the_gaussian_tail():
    """A static pixel with exact Gaussian σ: until its first restart z = (r − r̄)/
    sqrt(σ² + σ̄²) is N(0, 1) for every history, so the tests up to each pixel's first
    restart fail at the rate 1 − confidence (binomial 5σ band).  (A false restart
    starts the history from an outlier, so the next frames restart more often: the
    overall rate on a simulated scene is in docs/frames.md.)"""
    rng = np.random.default_rng(11)
    conf = 0.99
    fus = TemporalFusion(2, W, conf)
    clean = np.ones(2 * W, bool)  # no restart yet
    n_tests = n_first = 0
    for i in range(150):
        sig = rng.uniform(0.005, 0.05, size=2 * W)
        r = 5.0 + sig * rng.standard_normal(2 * W)
        c = frame_cloud(r, sig, t=i, pixels=np.tile(np.arange(W), 2))
        c.attributes["row"] = np.repeat([0, 1], W).astype(np.int32)
        age = fus.update(c)["age"]
        if i:
            n_tests += int(clean.sum())
            first = clean & (age == 1)
            n_first += int(first.sum())
            clean &= ~first
    assert fus.tests == 149 * 2 * W and fus.restarts >= n_first
    lo, hi = binom.ppf([norm.cdf(-5), norm.cdf(5)], n_tests, 1 - conf)
    assert lo <= n_first <= hi, (n_first, n_tests * (1 - conf))


@pytest.mark.parametrize("bad", [0.0, np.nan])
def test_points_without_a_finite_sigma_pass_alone_and_reset_the_pixel(bad):
    fus = TemporalFusion(1, W, 0.997)
    fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=0))
    sig = np.full(W, 0.01)
    sig[7] = bad
    out = fus.update(frame_cloud(np.full(W, 2.0), sig, t=1))
    assert out["age"][7] == 1 and out["age"][8] == 2
    out = fus.update(frame_cloud(np.full(W, 2.0), 0.01, t=2))
    assert out["age"][7] == 1 and out["age"][8] == 3


def test_frames_that_scatter_beyond_their_sigma_inflate_it_by_the_birge_ratio():
    """Ranges alternating ±2σ about 3 m (inside the k = 2.97 bound, never a restart):
    χ² = Σ w (r − r̄)², and σ_r is (Σw)^−½ · sqrt(χ²/(n − 1))."""
    fus = TemporalFusion(1, W, 0.997)
    sig = 0.02
    r = 3.0 + 2 * sig * np.array([1, -1, 1, -1, 1, -1])
    for i, ri in enumerate(r):
        out = fus.update(frame_cloud(np.full(W, ri), sig, t=i))
    w = np.full(r.size, 1 / sig ** 2)
    mean = (w * r).sum() / w.sum()
    chi2 = (w * (r - mean) ** 2).sum()
    assert np.all(out["age"] == 6)
    np.testing.assert_allclose(out["range"], mean, rtol=1e-12)
    np.testing.assert_allclose(out["sigma_r"], np.sqrt(chi2 / 5 / w.sum()), rtol=1e-9)
    np.testing.assert_allclose(out["sigma_z"], out["sigma_r"], rtol=1e-9)  # σ_z = σ_r here


def constant_systematic(sigma_sys):
    """A ``systematic`` callable: every point's common σ is ``sigma_sys`` along z."""
    def common(cloud):
        n = len(cloud)
        dx = np.zeros((n, 3))
        dx[:, 2] = sigma_sys
        return Systematic(np.full(n, sigma_sys), dx)
    return common


def test_the_common_part_of_the_error_does_not_average_down():
    """Monte Carlo: each pixel's frames share one bias b ~ N(0, σ_sys²) and add their own
    noise ε ~ N(0, σ_i²).  After 20 frames the fused range's error b + Σwε/Σw has the
    variance σ_sys² + 1/Σw: its pulls against the fused σ_r are N(0, 1) (χ² band), while
    the σ of the random part alone would give pulls of sqrt(1 + σ_sys²·Σw) ≈ 2.6."""
    rng = np.random.default_rng(5)
    n_pix, n_frames, s_sys = 2000, 20, 0.02
    fus = TemporalFusion(1, n_pix, 0.997, systematic=constant_systematic(s_sys))
    bias = s_sys * rng.standard_normal(n_pix)
    sig = rng.uniform(0.03, 0.06, size=(n_frames, n_pix))
    r = 4.0 + bias + sig * rng.standard_normal((n_frames, n_pix))
    for i in range(n_frames):
        out = fus.update(frame_cloud(r[i], sig[i], t=0.1 * i, pixels=np.arange(n_pix)))
    live = out["age"] == n_frames  # (a few false restarts: those pixels start again)
    assert live.mean() > 0.9
    w = 1.0 / sig ** 2
    mean = (w * r).sum(0) / w.sum(0)
    birge = np.sqrt(np.maximum((w * (r - mean) ** 2).sum(0) / (n_frames - 1), 1.0))
    s_rand = birge / np.sqrt(w.sum(0))
    s_z = birge * np.sqrt((w ** 2 * sig ** 2).sum(0)) / w.sum(0)
    np.testing.assert_allclose(out["range"][live], mean[live], rtol=1e-12)
    np.testing.assert_allclose(out["sigma_r"][live], np.hypot(s_rand, s_sys)[live], rtol=1e-9)
    np.testing.assert_allclose(out["sigma_z"][live], np.hypot(s_z, s_sys)[live], rtol=1e-9)
    np.testing.assert_allclose(out["sigma_x"][live], (0.1 * s_z)[live], rtol=1e-9)
    pulls = (out["range"] - 4.0)[live] / out["sigma_r"][live]
    lo, hi = chi2.ppf([norm.cdf(-5), norm.cdf(5)], live.sum()) / live.sum()
    assert lo <= np.mean(pulls ** 2) <= hi, np.mean(pulls ** 2)
    naive = (out["range"] - 4.0)[live] / s_rand[live]
    assert np.mean(naive ** 2) > 4.0  # without the floor the σ would be 2.6 times too small


def test_the_agreement_test_sees_only_the_random_part():
    """A common part (σ_sys 1 m) leaves the bound k·sqrt(σ_r² + σ̄_rand²) as it is: a jump
    of 9 cm on σ 2 cm restarts, 5 cm does not (as without a common part)."""
    fus = TemporalFusion(1, W, 0.997, systematic=constant_systematic(1.0))
    for i in range(4):
        fus.update(frame_cloud(np.full(W, 3.0), 0.02, t=i))
    step = np.where(np.arange(W) < W // 2, 0.05, 0.09)
    out = fus.update(frame_cloud(3.0 + step, 0.02, t=4))
    small = np.arange(W) < W // 2
    assert np.all(out["age"][small] == 5) and np.all(out["age"][~small] == 1)
    np.testing.assert_allclose(out["sigma_r"][~small], np.hypot(0.02, 1.0))
