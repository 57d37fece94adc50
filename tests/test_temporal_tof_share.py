"""The first-photon model's share of the time of flight, common to every frame of a pixel
(mems_stereo.pipeline.temporal.tof_model_share): checked against the first-photon delay
integrated here with SciPy, and in the temporal fusion, where a point carried by its time
of flight (a turning column) keeps it instead of averaging it down."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

import mems_stereo as ms
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.first_photon_correction import MODEL_DELAY_FRACTION, MU_MODEL_FACTOR
from mems_stereo.pipeline.scan_dwell import Systematic
from mems_stereo.pipeline.temporal import TemporalFusion, tof_model_share

SYSTEM = ms.preset("burkard2022")


def first_arrival(mu: float) -> float:
    """E[first photon's arrival − pulse centre] in pulse σ for Poisson(μ) photons of a
    Gaussian pulse, given one arrives: ∫ t μφ(t) e^(−μΦ(t)) dt / (1 − e^(−μ))."""
    num = quad(lambda t: t * mu * norm.pdf(t) * math.exp(-mu * norm.cdf(t)), -12, 12,
               points=[0.0])[0]
    return num / -math.expm1(-mu)


def cloud_of(delay, mu, w_stereo, r=6.5):
    n = len(delay)
    pts = np.zeros((n, 3))
    pts[:, 2] = r
    return PointCloud(pts, {"tof_delay": np.asarray(delay, float),
                            "signal_photons": np.asarray(mu, float),
                            "weight_stereo": np.asarray(w_stereo, float),
                            "pixel": np.arange(n, dtype=np.int32)})


@pytest.mark.parametrize("mu", [0.3, 0.6, 1.5])
def test_the_share_is_the_model_allowance_of_the_delay(mu):
    """σ = (1 − w_st)·c|d|/2·hypot(f_model, ½|δ(μF) − δ(μ/F)|/|δ(μ)|), δ integrated here."""
    F = MU_MODEL_FACTOR
    rel = 0.5 * abs(first_arrival(mu * F) - first_arrival(mu / F)) / abs(first_arrival(mu))
    d, w = -0.9e-9, np.array([0.0, 0.25, 1.0])
    got = tof_model_share(SYSTEM)(cloud_of(np.full(3, d), np.full(3, mu), w))
    want = (1 - w) * 0.5 * SYSTEM.speed_of_light * abs(d) * math.hypot(MODEL_DELAY_FRACTION, rel)
    np.testing.assert_allclose(got.sigma_r, want, rtol=1e-3)
    np.testing.assert_allclose(got.dx[:, 2], want, rtol=1e-3)  # along the ray (z here)
    assert got.sigma_r[2] == 0.0  # a point the stereo carries alone: nothing shared


def test_small_signal_limit():
    """δ ∝ μ for μ → 0: the relative change over μ/F … μF is (F − 1/F)/2."""
    F = MU_MODEL_FACTOR
    got = tof_model_share(SYSTEM)(cloud_of([-1e-10, np.nan], [1e-4, np.nan], [0.0, 0.0]))
    c = SYSTEM.speed_of_light
    want = 0.5 * c * 1e-10 * math.hypot(MODEL_DELAY_FRACTION, 0.5 * (F - 1 / F))
    np.testing.assert_allclose(got.sigma_r[0], want, rtol=1e-3)
    assert got.sigma_r[1] == 0.0  # no correction: nothing shared


def test_a_tof_carried_pixel_keeps_its_common_error_over_frames():
    """Monte Carlo: pixels carried by the ToF (w_st 0.06) whose frames share a bias
    b ~ N(0, σ_share²) (the first-photon model misjudging the level alike in every frame)
    plus their own noise.  After 20 frames the fusion's pulls are N(0, 1); the
    random part alone (systematic off) gives pulls over 2."""
    rng = np.random.default_rng(11)
    n_pix, n_frames = 600, 20
    delay, mu, w_st = -0.9e-9, 0.6, 0.06
    share = tof_model_share(SYSTEM)(cloud_of([delay], [mu], [w_st])).sigma_r[0]
    s_rand = 0.15
    bias = share * rng.standard_normal(n_pix)
    fused = {}
    for name, systematic in (("shared", tof_model_share(SYSTEM)), ("random only", nothing)):
        fus = TemporalFusion(1, n_pix, 0.997, systematic=systematic)
        fr = np.random.default_rng(12)
        for i in range(n_frames):
            r = 6.5 + bias + s_rand * fr.standard_normal(n_pix)
            out = fus.update(frame(r, np.hypot(s_rand, share), i, delay, mu, w_st))
        fused[name] = out
    for name, lo, hi in (("shared", 0.85, 1.2), ("random only", 2.0, np.inf)):
        out = fused[name]
        live = out["age"] == n_frames
        assert live.mean() > 0.9
        pulls = (out["range"] - 6.5)[live] / out["sigma_r"][live]
        assert lo <= np.sqrt(np.mean(pulls ** 2)) <= hi, (name, np.sqrt(np.mean(pulls ** 2)))


def nothing(cloud):
    """A ``systematic`` callable with no common part."""
    n = len(cloud)
    return Systematic(np.zeros(n), np.zeros((n, 3)))


def frame(r, sigma, t, delay, mu, w_st):
    """A frame of the line sensor: one point per pixel straight ahead of its column."""
    n = r.size
    pts = np.zeros((n, 3))
    pts[:, 2] = r
    return PointCloud(pts, {
        "counts": np.full(n, 35, np.int32), "pixel": np.arange(n, dtype=np.int32),
        "row": np.zeros(n, np.int32), "range": r, "sigma_r": np.full(n, sigma),
        "t": np.full(n, float(t)), "step_lo": np.full(n, 10, np.int32),
        "step_hi": np.full(n, 20, np.int32), "tof_delay": np.full(n, delay),
        "signal_photons": np.full(n, mu), "weight_stereo": np.full(n, w_st)})
