"""First-photon statistics of a SPAD pixel behind a TDC.

Moments of the first signal photon's arrival (tabulated), the posterior of
the signal level from the firing pattern across the spot, and the CDF/mean
delay of the first of Poisson(μ) return photons used by the simulator.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import ndtr

from mems_stereo.physics.pulse import PulseShape

# --------------------------------------------------------------------------
# first-photon bias of the time-of-flight estimate
#
# A SPAD pixel records only its first photon per shot, and the TDC nothing
# before it starts.  With μ_w signal photons per shot arriving after the TDC
# start (Poisson), from a Gaussian pulse of σ centred at TDC time τ0, the
# recorded arrival u (relative to τ0, on u ≥ a = −τ0/σ in σ units) is the
# first of them: survival S(u) = (exp(−μ_w F(u)) − exp(−μ_w)) / (1 − exp(−μ_w))
# with F the pulse's distribution truncated to u ≥ a.  Its mean is early by
# up to ≈ −σ·sqrt(2 ln μ_w) for a strong return and late near τ0 ≈ 0 (the
# early part of the pulse is cut off); its variance is below σ².  (The same
# model as mems_stereo.physics.first_photon_timing.first_photon_moments with no
# background, and as the simulator's sampling; tests/test_tof_bias.py checks all three agree.)

#: most signal photons per shot the correction considers
MU_MAX = 100.0
_A_GRID = (-6.0, 4.0, 101)  # a = −τ0/σ: below −6 the cut does nothing
_LOGMU_GRID = (math.log(1e-4), math.log(MU_MAX), 97)


def first_photon_moments(a, mu_window, n_quad: int = 801):
    """Mean and variance of a first-photon arrival, in units of the pulse σ.

    Parameters
    ----------
    a : (...) float64, the TDC start relative to the pulse centre, in σ
        (``−τ0/σ``; −inf: no cut).
    mu_window : (...) float64 > 0, expected signal photons per shot that
        arrive after the TDC start (so that ``1 − exp(−μ_w)`` is the
        probability of a signal detection).
    n_quad : trapezoid nodes over the 16σ after ``max(a, −8)``.

    Returns
    -------
    mean, var : (...) float64 (broadcast shape), the arrival time's mean
        relative to the pulse centre and its variance, in σ and σ².
    """

    a, mu = np.broadcast_arrays(np.asarray(a, dtype=np.float64),
                                np.asarray(mu_window, dtype=np.float64))
    lo = np.maximum(a, -8.0)[..., None]
    t = np.linspace(0.0, 16.0, n_quad)
    u = lo + t
    # 1 − F(u) of the truncated Gaussian, from the upper tails (no cancellation)
    tail = ndtr(-u) / ndtr(-lo)
    m = mu[..., None]
    e_mu = np.exp(-m)
    with np.errstate(invalid="ignore", divide="ignore"):
        surv = np.where(m > 1e-9, (np.exp(-m * (1.0 - tail)) - e_mu) / -np.expm1(-m), tail)
    w = np.full(n_quad, t[1] - t[0])
    w[0] = w[-1] = 0.5 * (t[1] - t[0])
    m1 = surv @ w  # E[u − lo]
    m2 = 2.0 * ((surv * t) @ w)  # E[(u − lo)²]
    return lo[..., 0] + m1, np.maximum(m2 - m1 * m1, 0.0)


@functools.lru_cache(maxsize=1)
def _first_photon_table():
    """(a grid, log μ_w grid, mean, var) of :func:`first_photon_moments`, tabulated once."""
    ag = np.linspace(*_A_GRID)
    lg = np.linspace(*_LOGMU_GRID)
    mean = np.empty((ag.size, lg.size))
    var = np.empty_like(mean)
    for i, a in enumerate(ag):  # row by row: the temporaries stay (n_mu, n_quad)
        mean[i], var[i] = first_photon_moments(a, np.exp(lg))
    return ag, lg, mean, var


def _table_lookup(a, logmu):
    """Bilinear look-up of (mean, var) on the table; arguments clipped to its grid.

    ``a`` and ``logmu`` broadcast against each other; the arithmetic is done on
    their own shapes (``a`` is usually one value per peak) and the four corners
    are gathered from the flattened tables, so an (Q, 1, 1) ``a`` against a
    (Q, J, B) ``logmu`` costs no (Q, J, B) index arrays for ``a``.
    """
    ag, lg, mean, var = _first_photon_table()
    fa = np.clip((np.asarray(a, dtype=np.float64) - ag[0]) / (ag[1] - ag[0]), 0.0,
                 ag.size - 1.000001)
    fm = np.clip((np.asarray(logmu, dtype=np.float64) - lg[0]) / (lg[1] - lg[0]), 0.0,
                 lg.size - 1.000001)
    i, j = fa.astype(np.int64), fm.astype(np.int64)
    wa, wm = fa - i, fm - j
    n = lg.size
    k00 = i * n + j  # flat index of corner (i, j); (i+1, j) is +n, (i, j+1) is +1
    c00, c10, c01, c11 = (1 - wa) * (1 - wm), wa * (1 - wm), (1 - wa) * wm, wa * wm
    out = []
    for t in (mean.ravel(), var.ravel()):
        out.append(c00 * t[k00] + c10 * t[k00 + n] + c01 * t[k00 + 1] + c11 * t[k00 + n + 1])
    return out[0], out[1]


#: grid of the signal photons per shot μ0 (spot centred on the pixel) of the posterior
MU_GRID = np.exp(np.linspace(math.log(1e-2), math.log(MU_MAX), 41))
#: probability that a shot gives an inlier the spot model cannot explain (background
#: inside the window, crosstalk): keeps one stray detection from forcing μ0 up
OUTLIER_PROBABILITY = 0.02


def _detection_log_odds(f):
    """log p − log(1 − p) of a shot with spot share f (…) on the μ0 grid -> (…, J)."""
    p = _firing_probability(f)
    return np.log(p) - np.log1p(-p)


def _firing_probability(f):
    """P(inlier) of a shot with spot share f (…) on the μ0 grid -> (…, J), in (0, 1)."""
    e = OUTLIER_PROBABILITY
    pf = -np.expm1(-MU_GRID * np.asarray(f, dtype=np.float64)[..., None])
    return np.minimum(e + (1 - e) * pf, 1.0 - 1e-12)


def first_photon_delay(log_likelihood, f_band, n_band, tau0, sigma):
    """Posterior first-photon delay of peaks from their spot-profile likelihood.

    Parameters
    ----------
    log_likelihood : (Q, J) log-likelihood of μ0 = :data:`MU_GRID` (signal
        photons per shot after the TDC start with the spot centred on the
        pixel); the prior is uniform in log μ0 over the grid.
    f_band, n_band : (Q, B) spot shares and valid shots of the angle steps
        around each peak's band (n 0 pads).
    tau0 : (Q,) s, TDC time of each pulse's centre (``L/c + offset``); it
        matters only near the TDC start, where the early part of the pulse
        is cut off (give it from the stereo or fused point there: inverting
        the mean arrival time is ill-conditioned at the cut).
    sigma : float, s, the pulse σ (⊕ jitter).

    Returns
    -------
    delay : (Q,) s, E[mean arrival − pulse centre] of the detections (the
        average over the band's shots of δ(a, μ0·f_s) weighted by their
        detection probabilities, then over the posterior of μ0).
    sigma_delay : (Q,) s, its posterior standard deviation.
    var_arrival : (Q,) s², E[variance of one detection's arrival] (the
        band's mixture of first-photon spreads).
    mu : (Q,) posterior mean of μ0.
    """
    ll = np.asarray(log_likelihood, dtype=np.float64)
    post = np.exp(ll - ll.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)  # (Q, J)
    mu_s = MU_GRID[None, :, None] * f_band[:, None, :]  # (Q, J, B)
    w = n_band[:, None, :] * -np.expm1(-mu_s)  # expected detections per step
    w = w / np.maximum(w.sum(axis=2, keepdims=True), 1e-300)
    lm = np.log(np.clip(mu_s, 1e-4, MU_MAX))
    a = -np.asarray(tau0, dtype=np.float64) / sigma
    d, v = _table_lookup(a[:, None, None], lm)
    dj = np.sum(w * d, axis=2)  # (Q, J) mean delay of the band for each μ0
    vj = np.sum(w * (v + d * d), axis=2) - dj * dj  # mixture variance
    dm = np.sum(post * dj, axis=1)
    sd = np.sqrt(np.maximum(np.sum(post * dj * dj, axis=1) - dm * dm, 0.0))
    return dm * sigma, sd * sigma, np.sum(post * vj, axis=1) * sigma ** 2, post @ MU_GRID


def first_photon_cdf(s, mu, pulse: PulseShape) -> np.ndarray:
    """CDF of the first of Poisson(μ) return photons' delay, given at least one.

    ``(1 − exp(−μ F(s))) / (1 − exp(−μ))`` with F the pulse (⊗ jitter) CDF;
    no background and no window.  ``s`` (...) seconds; returns (...) float64.
    """
    return -np.expm1(-mu * pulse.cdf_at(s)) / -math.expm1(-mu)


def first_photon_mean_delay(mu, pulse: PulseShape) -> np.ndarray:
    """Mean delay (s) of the first return photon given ≥ 1, for each μ in ``mu``.

    The pile-up bias of the laser return itself: 0 for μ → 0 (symmetric
    pulse), earlier (negative) as μ grows.  Integrates :func:`first_photon_cdf`
    on the pulse's grid: E[s] = t_max − ∫ G(s) ds over the grid.
    """
    m = np.atleast_1d(np.asarray(mu, dtype=np.float64))
    out = np.empty(m.shape)
    for i, mi in enumerate(m.ravel()):
        g = pulse.cdf if mi <= 1e-9 else -np.expm1(-mi * pulse.cdf) / -math.expm1(-mi)
        out.ravel()[i] = pulse.t[-1] - np.trapezoid(g, pulse.t)
    return out.reshape(np.shape(mu))
