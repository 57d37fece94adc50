"""First-photon timing model (mems_stereo.physics.first_photon_timing) against a Monte-Carlo of photons."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mems_stereo.physics.first_photon_timing import FirstPhotonTable, first_photon_moments
from mems_stereo.physics.pulse import pulse_sigma

SIGMA = pulse_sigma(14.9e-9)


def _monte_carlo(mu, tau0, lam, rng, n=200_000):
    """First photon per shot: Poisson(μ) Gaussian signal photons, exponential background,
    nothing before τ = 0; returns detection probability, mean and std of signal detections."""
    k = rng.poisson(mu, n)
    t = np.repeat(np.full(n, tau0), k) + SIGMA * rng.standard_normal(k.sum())
    t[t < 0] = np.inf
    first = np.full(n, np.inf)
    np.minimum.at(first, np.repeat(np.arange(n), k), t)
    bg = rng.exponential(1 / lam, n) if lam > 0 else np.full(n, np.inf)
    sig = np.isfinite(first) & (first < bg)
    return sig.mean(), first[sig].mean() - tau0, first[sig].std()


@pytest.mark.parametrize("mu,tau0,lam", [(0.3, 40e-9, 0.0), (5.0, 30e-9, 0.0),
                                         (2.0, 2e-9, 0.0), (1.0, 10e-9, 6e6)])
def test_moments_match_monte_carlo(mu, tau0, lam):
    rng = np.random.default_rng(7)
    p_mc, m_mc, s_mc = _monte_carlo(mu, tau0, lam, rng)
    p, m, v = first_photon_moments([-tau0], mu, SIGMA, lam)
    n_sig = 200_000 * p_mc
    assert abs(p[0] - p_mc) < 4 * math.sqrt(p_mc * (1 - p_mc) / 200_000) + 1e-4
    assert abs(m[0] - m_mc) < 4 * s_mc / math.sqrt(n_sig)
    assert abs(math.sqrt(v[0]) - s_mc) < 0.02 * s_mc


def test_bias_signs():
    """Strong returns arrive early (first of many photons); a cut pulse arrives late."""
    _, m_strong, _ = first_photon_moments([-100e-9], 10.0, SIGMA)
    _, m_weak, _ = first_photon_moments([-100e-9], 1e-3, SIGMA)
    _, m_cut, _ = first_photon_moments([0.0], 1e-3, SIGMA)
    assert m_strong[0] < -1.4 * SIGMA
    assert abs(m_weak[0]) < 0.01 * SIGMA
    # weak return centred at the TDC start: half-normal mean σ·sqrt(2/π)
    assert m_cut[0] == pytest.approx(SIGMA * math.sqrt(2 / math.pi), rel=2e-3)


def test_table_interpolates_direct_values():
    tab = FirstPhotonTable(SIGMA, 1e5, 312.5e-12)
    for tau0, mu in [(7.3e-9, 2.2), (25e-9, 0.7)]:
        p, m, v = first_photon_moments([-tau0], mu, SIGMA, 1e5)
        assert tab.mean_time(tau0, math.log(mu)) == pytest.approx(tau0 + m[0], abs=0.02e-9)
        assert tab.probability(tau0, math.log(mu)) == pytest.approx(p[0], abs=2e-3)
        assert tab.std(tau0, math.log(mu)) == pytest.approx(
            math.sqrt(v[0] + 312.5e-12 ** 2 / 12), rel=0.01)
