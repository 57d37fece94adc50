"""The variance of a peak's mean scan angle: binomial where the scan revisits its
angles (``first_photon_correction.angle_binomial_factor``)."""

from __future__ import annotations

import numpy as np

from mems_stereo.pipeline.first_photon_correction import (
    BINOMIAL_MIN_SHOTS,
    angle_binomial_factor,
)


def _profile(B=121, width=51.0, blur=8.0):
    """(steps (1, B), f (1, B)): a pixel's share of a blurred spot over the steps."""
    from scipy.special import ndtr

    s = np.arange(B, dtype=np.float64)
    c = (B - 1) / 2
    f = ndtr((s - c + width / 2) / blur) - ndtr((s - c - width / 2) / blur)
    return s[None, :], f[None, :]


def _mc_ratio(n_shots, mu, seed, trials=4000):
    """Monte-Carlo variance of θ̄ (firings binomial given the shots per step) against
    the Poisson form Σ N p (θ − θ̄)² / K²; and the factor for the same band."""
    steps, f = _profile()
    n = np.asarray(n_shots, np.float64)
    p = -np.expm1(-mu * f[0])
    rng = np.random.default_rng(seed)
    k = rng.binomial(n.astype(np.int64)[None, :], p[None, :], size=(trials, n.size))
    K = k.sum(axis=1)
    k = k[K > 0]
    tb = (k * steps).sum(axis=1) / K[K > 0]
    theta_bar = np.sum(n * p * steps[0]) / np.sum(n * p)
    v_pois = np.sum(n * p * (steps[0] - theta_bar) ** 2) / np.sum(n * p) ** 2
    fac = angle_binomial_factor(steps, n[None, :], np.where(n > 0, f, 0.0)[None, 0],
                                np.array([mu]), np.array([theta_bar]))[0]
    return np.var(tb) / v_pois, fac


def test_saturated_revisited_angles_match_monte_carlo():
    # every third step sampled by 6 shots (a scan that revisits its angles)
    n = np.zeros(121)
    n[::3] = 6
    for mu in (0.3, 2.0, 8.0):
        ratio, fac = _mc_ratio(n, mu, seed=int(mu * 10))
        assert abs(fac - ratio) < 0.1 * max(ratio, 0.05) + 0.02, (mu, fac, ratio)
    _, fac_sat = _mc_ratio(n, 8.0, seed=1)
    _, fac_weak = _mc_ratio(n, 0.05, seed=2)
    assert fac_sat < 0.3 < 0.9 < fac_weak <= 1.0


def test_sparse_or_undetermined_peaks_keep_the_poisson_variance():
    steps, f = _profile()
    n = np.zeros((1, 121))
    n[0, ::7] = 1  # one shot per sampled angle: below BINOMIAL_MIN_SHOTS
    assert BINOMIAL_MIN_SHOTS > 1
    fac = angle_binomial_factor(steps, n, np.where(n > 0, f, 0.0), np.array([20.0]),
                                np.array([60.0]))
    assert fac[0] == 1.0
    # no shots at all, or no μ0: 1
    z = np.zeros((1, 121))
    assert angle_binomial_factor(steps, z, z, np.array([1.0]), np.array([60.0]))[0] == 1.0
    nn = np.full((1, 121), 5.0)
    assert angle_binomial_factor(steps, nn, f, np.array([np.nan]), np.array([60.0]))[0] == 1.0


def test_mean_angle_bias_matches_monte_carlo_where_the_shots_bunch():
    """Near a turning point the shots bunch on one side of the footprint: the mean
    firing angle moves towards it by what ``mean_angle_bias`` predicts; with the
    shots spread evenly the prediction is zero."""
    from mems_stereo.pipeline.first_photon_correction import mean_angle_bias

    steps, f = _profile()
    c = (steps.size - 1) / 2
    for mu in (0.5, 4.0):
        even = np.full((1, steps.size), 3.0)
        assert abs(mean_angle_bias(steps, even, f, f, np.array([mu]))[0]) < 1e-9
        dense = np.rint(3.0 * np.exp((steps[0] - c) / 30.0))[None, :]  # shots grow to one side
        b = mean_angle_bias(steps, dense, f, f, np.array([mu]))[0]
        rng = np.random.default_rng(int(mu * 100))
        p = -np.expm1(-mu * f[0])
        k = rng.binomial(dense.astype(np.int64), p[None, :], size=(3000, steps.size))
        tb = (k * steps).sum(axis=1) / k.sum(axis=1)
        assert b > 3.0  # steps, towards the denser side
        assert abs((np.mean(tb) - c) - b) < 0.05 * b + 4 * np.std(tb) / np.sqrt(tb.size)
