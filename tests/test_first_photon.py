"""The first-photon model with background (mems_stereo.physics.first_photon) against a Monte-Carlo of photons."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mems_stereo.physics.first_photon import first_photon_signal, first_photon_timing
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
    p, m, v = first_photon_timing([tau0], mu, SIGMA, lam)
    n_sig = 200_000 * p_mc
    assert abs(p[0] - p_mc) < 4 * math.sqrt(p_mc * (1 - p_mc) / 200_000) + 1e-4
    assert abs(m[0] - m_mc) < 4 * s_mc / math.sqrt(n_sig)
    assert abs(math.sqrt(v[0]) - s_mc) < 0.02 * s_mc


def test_bias_signs():
    """Strong returns arrive early (first of many photons); a cut pulse arrives late."""
    _, m_strong, _ = first_photon_timing([100e-9], 10.0, SIGMA)
    _, m_weak, _ = first_photon_timing([100e-9], 1e-3, SIGMA)
    _, m_cut, _ = first_photon_timing([0.0], 1e-3, SIGMA)
    assert m_strong[0] < -1.4 * SIGMA
    assert abs(m_weak[0]) < 0.01 * SIGMA
    # weak return centred at the TDC start: half-normal mean σ·sqrt(2/π)
    assert m_cut[0] == pytest.approx(SIGMA * math.sqrt(2 / math.pi), rel=2e-3)


def _density_quadrature(a, mu_w, b, n=200_001):
    """Independent check: the signal-first density h = μ_w f(u) exp(−μ_w F(u) − b (u − a))
    integrated directly on a fine grid, dense at the cut (f, F the pulse truncated to
    u ≥ a), σ units."""
    from scipy.special import ndtr

    u = a + 16.0 * np.linspace(0.0, 1.0, n) ** 3
    q = ndtr(-a)
    f = np.exp(-0.5 * u * u) / math.sqrt(2 * math.pi) / q
    F = (q - ndtr(-u)) / q
    h = mu_w * f * np.exp(-mu_w * F - b * (u - a))
    p = np.trapezoid(h, u)
    m = np.trapezoid(h * u, u) / p
    return p, m, np.trapezoid(h * u * u, u) / p - m * m


@pytest.mark.parametrize("a,mu_w,b", [(-3.0, 0.2, 0.0), (-1.0, 5.0, 0.05), (0.5, 40.0, 0.2),
                                      (2.5, 80.0, 0.0), (-4.0, 1e-6, 0.5), (3.9, 1e-3, 1.0)])
def test_by_parts_quadrature_matches_density_quadrature(a, mu_w, b):
    """The integrated-by-parts form (G, no cancellation) equals the density integrated
    directly on a 250× finer grid, including a spike at the cut (μ_w = 80, a = 2.5):
    to the default grid's trapezoid error, and closely on a 10× finer grid (the
    formula is exact; only the quadrature differs)."""
    p0, m0, v0 = _density_quadrature(a, mu_w, b)
    p, m, v = (float(x) for x in first_photon_signal(a, mu_w, b))
    assert p == pytest.approx(p0, rel=1e-3)
    assert m == pytest.approx(m0, abs=1e-2)
    assert v == pytest.approx(v0, abs=5e-3)
    p, m, v = (float(x) for x in first_photon_signal(a, mu_w, b, n_quad=8001))
    assert p == pytest.approx(p0, rel=1e-5)
    assert m == pytest.approx(m0, abs=1e-4)
    assert v == pytest.approx(v0, abs=5e-5)


def test_weak_signal_limit_is_continuous():
    """μ_w → 0: p → 0 linearly, the moments tend to those of the pulse after the cut."""
    p0, m0, v0 = first_photon_signal(-0.5, 0.0, 0.1)
    p1, m1, v1 = first_photon_signal(-0.5, 1e-9, 0.1)
    assert p0 == 0.0 and p1 == pytest.approx(1e-9 * p1 / 1e-9) and 0 < p1 < 1e-9
    assert m0 == pytest.approx(m1, abs=1e-9) and v0 == pytest.approx(v1, abs=1e-9)


def test_background_before_the_pulse_fires_the_pixel_first():
    """A pulse 20σ after the TDC start with b background photons per σ: the signal is
    first only if nothing came in those 20σ, p = e^{−20 b}(1 − e^{−μ}) to first order."""
    b = 0.02
    p, _, _ = first_photon_signal(-20.0, 2.0, b)
    p0, _, _ = _density_quadrature(-8.0, 2.0, b)
    assert float(p) == pytest.approx(math.exp(-12 * b) * p0, rel=1e-6)
    assert float(p) < (1 - math.exp(-2.0)) * math.exp(-20 * b) * 1.1
