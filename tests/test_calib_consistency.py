"""The flat-wall consistency test: the expected information of the first-photon
cells, and a score test that holds its size when the wall's nuisance includes
parameters shared with other walls (else correct fits are refused as "not a
flat wall")."""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.expected_info import cell_fisher
from mems_stereo.calib.problem import Cells, cell_terms
from scipy.special import ndtr, ndtri

SIGMA = 6.3e-9
T_MAX = 250e-9


def _first_photons(rng, n, tau, m, lam):
    """(n,) first-photon times on [0, T_MAX] (NaN: none) of λ + m·φ((t−τ)/σ)/σ."""
    z0, z1 = -tau / SIGMA, (T_MAX - tau) / SIGMA
    p = ndtr(z1) - ndtr(z0)
    k = rng.poisson(m * p, n)
    # the first of k truncated-normal arrivals: CDF quantile 1 − (1 − u)^(1/k)
    u = rng.random(n)
    q = -np.expm1(np.log1p(-u) / np.maximum(k, 1))
    t_sig = np.where(k > 0, tau + SIGMA * ndtri(ndtr(z0) + p * q), np.inf)
    t_bg = rng.exponential(1.0 / lam, n)
    t = np.minimum(t_sig, t_bg)
    return np.where(t <= T_MAX, t, np.nan)


def _cells(t, lam):
    n = t.size
    return Cells(np.arange(n), np.full(n, 10.0), np.zeros(n), t, np.full(n, lam), T_MAX,
                 np.arange(n), 0.0)


def test_cell_fisher_is_the_variance_of_the_cell_scores():
    """F of :func:`cell_fisher` against the Monte-Carlo covariance of the exact
    scores ∂ℓ/∂τ and ∂ℓ/∂m of :func:`cell_terms`: weak and piled-up returns, the
    TDC start cutting the pulse, dense background."""
    rng = np.random.default_rng(5)
    n = 200_000
    for tau, m, lam in ((40e-9, 0.1, 2e5), (30e-9, 3.0, 5e6), (4e-9, 0.7, 1e4),
                        (60e-9, 0.05, 6e6)):
        t = _first_photons(rng, n, tau, m, lam)
        c = _cells(t, lam)
        # pixel 10, spot centred on it and wide: share ~ 1, log μ = log(m / share)
        from mems_stereo.calib.problem import spot_share

        share = float(spot_share(np.array([10.0]), np.array([10.0]), 6.0)[0][0])
        pred = np.tile([tau, 10.0, 0.0, 0.0], (n, 1))
        _, d = cell_terms(c, pred, math.log(m / share), math.log(6.0), SIGMA, False)
        s_tau, s_m = d[:, 0], d[:, 3] / m
        assert abs(s_tau.mean()) < 5 * s_tau.std() / math.sqrt(n)
        emp = np.cov(np.stack([s_tau, s_m]))
        F = cell_fisher(np.array([tau]), np.array([m]), np.array([lam]), T_MAX, SIGMA)[0]
        assert abs(emp[0, 0] / F[0] - 1) < 0.03, (tau, m, lam, emp[0, 0], F[0])
        assert abs(emp[1, 1] / F[2] - 1) < 0.03, (tau, m, lam, emp[1, 1], F[2])
        assert abs(emp[0, 1] - F[1]) < 0.03 * math.sqrt(F[0] * F[2])


def test_score_test_holds_its_size_with_shared_nuisance():
    """Scores drawn under the model at the true parameters: the wall's own score of
    a shared nuisance (a system parameter the other walls also fix) is not zero,
    and a quarter's time shift nearly collinear with it (a time trend across the
    sensor vs the wall's yaw) must not inherit that pull (C(α) effective score).
    The p-values are then uniform; without the adjustment most would be tiny."""
    rng = np.random.default_rng(11)
    n, trials = 4000, 300
    col = rng.uniform(0, 192, n)
    q = np.clip((col / 192 * 4).astype(int), 0, 3)
    p_vals = []
    for _ in range(trials):
        S = rng.normal(size=(n, 3))
        trend = (q - 1.5) / 1.5
        d = np.empty((n, 2))
        # the time score: mostly the nuisance's direction times a trend, plus a little of its own
        d[:, 0] = trend * S[:, 0] + 0.05 * rng.normal(size=n)
        d[:, 1] = rng.normal(size=n)
        p_vals.append(obs.consistency_scores(d, S, col).p_value)
    p_vals = np.array(p_vals)
    assert np.mean(p_vals < 0.01) < 0.04, np.mean(p_vals < 0.01)
    assert np.mean(p_vals < 0.5) > 0.35
    assert p_vals.min() > 1e-6
