"""First-photon statistics of a SPAD pixel behind a TDC.

Moments of the first signal photon's arrival (tabulated), the posterior of
the signal level from the firing pattern across the spot, and the CDF/mean
delay of the first of Poisson(μ) return photons used by the simulator.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import ndtr

from mems_stereo.physics.first_photon_kernel import band_kernel, band_moments, firing_kernels
from mems_stereo.physics.pulse import FWHM_PER_SIGMA, PulseShape

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
# early part of the pulse is cut off); its variance is below σ².  One
# implementation, first_photon_signal, with background as an option; the simulator
# samples the same process; tests/test_tof_bias.py and tests/test_first_photon.py check
# it against Monte-Carlo photons and the simulator's CDF.

#: most signal photons per shot the correction considers
MU_MAX = 100.0
_A_GRID = (-6.0, 4.0, 101)  # a = −τ0/σ: below −6 the cut does nothing
_LOGMU_GRID = (math.log(1e-4), math.log(MU_MAX), 97)


def first_photon_signal(a, mu_window, lam=0.0, n_quad: int = 801):
    """Probability, mean and variance of a first-photon detection on a signal photon.

    The one first-photon model of the package (the fusion's table, the
    calibration's start values and the tests' oracles all use it; the
    simulator samples the same process photon by photon).  A pixel fires on
    the first of its photons after the TDC start: signal photons of a
    Gaussian pulse (σ = 1 here), Poisson with ``mu_window`` expected after
    the start, and background photons at ``lam`` per σ.  With
    ``G(t) = e^{−μ_w}·expm1(μ_w·Φ_w(t))`` (``Φ_w`` the share of the pulse
    after ``t = u − lo``, ``lo = max(a, −8)``: the probability that no signal
    photon came before ``t`` but one comes later) and ``b = lam``, the
    signal-first density is ``−G′ e^{−bt}``; integrated by parts every
    moment is an integral of the smooth, positive ``G`` (trapezoid over
    ``T`` = 16σ; accurate where the density is a spike at the cut, and no
    cancellation for weak signals)::

        p       = G(0) − G(T) e^{−bT} − b ∫G e^{−bt}
        E[t·1]  = ∫G e^{−bt} (1 − b t) − T G(T) e^{−bT}
        E[t²·1] = ∫G e^{−bt} (2t − b t²) − T² G(T) e^{−bT}

    Parameters
    ----------
    a : (...) float64, the TDC start relative to the pulse centre, in σ
        (``−τ0/σ``; −inf: no cut, the quadrature starts at −8σ).
    mu_window : (...) float64 ≥ 0, expected signal photons per shot that
        arrive after the start (``μ·Φ(−a)`` for μ photons in the whole pulse).
    lam : (...) float64 ≥ 0, background photons per σ (rate × σ) that may
        fire the pixel first, from the start ``a`` on (with no start, ``a =
        −inf``, a pixel with background never fires first on the signal).
    n_quad : trapezoid nodes over the 16σ after ``max(a, −8)``.

    Returns
    -------
    p, mean, var : (...) float64 (broadcast shape): the probability that the
        pixel fires first on a signal photon, and the mean and variance of
        that photon's arrival relative to the pulse centre, in σ and σ²
        (their weak-signal limit where ``mu_window`` is 0).
    """
    a, mu, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64),
                                   np.asarray(mu_window, dtype=np.float64),
                                   np.asarray(lam, dtype=np.float64))
    lo = np.maximum(a, -8.0)[..., None]
    t = np.linspace(0.0, 16.0, n_quad)
    # share of the truncated pulse after t, from the upper tails (no cancellation);
    # computed once per distinct lo (a table row has one a for many μ)
    lo_u, inv = np.unique(lo, return_inverse=True)
    tail = (ndtr(-(lo_u[:, None] + t)) / ndtr(-lo_u)[:, None])[inv.reshape(lo.shape[:-1])]
    # μ_w → 0: G/μ_w → tail, so a floor keeps the weak-signal shape and p is rescaled
    m = np.maximum(mu, 1e-12)[..., None]
    G = np.expm1(m * tail)
    G *= np.exp(-m)
    if np.any(b):
        G *= np.exp(-b[..., None] * t)  # G(t) e^{−bt}
    w = np.full(n_quad, t[1] - t[0])
    w[0] = w[-1] = 0.5 * (t[1] - t[0])
    T = t[-1]
    G_T = G[..., -1]
    i012 = G @ np.stack([w, w * t, w * t * t], axis=1)
    i0, i1, i2 = i012[..., 0], i012[..., 1], i012[..., 2]
    p = G[..., 0] - G_T - b * i0
    e1 = i0 - b * i1 - T * G_T
    e2 = 2.0 * i1 - b * i2 - T * T * G_T
    with np.errstate(invalid="ignore", divide="ignore"):
        m1 = e1 / p
        var = np.maximum(e2 / p - m1 * m1, 0.0)
    # background that arrived between the TDC start and −8σ fired the pixel already
    with np.errstate(invalid="ignore"):
        early = np.where(b > 0, np.exp(-b * (lo[..., 0] - a)), 1.0)
    return p * (mu / m[..., 0]) * early, lo[..., 0] + m1, var


def first_photon_moments(a, mu_window, n_quad: int = 801):
    """Mean and variance of a first-photon arrival without background, in units of the pulse σ.

    :func:`first_photon_signal` with ``lam = 0``: see there for ``a`` and
    ``mu_window``.  Returns ``mean, var`` (...) float64, the arrival's mean
    relative to the pulse centre and its variance, in σ and σ².
    """
    _, mean, var = first_photon_signal(a, mu_window, 0.0, n_quad)
    return mean, var


def first_photon_timing(tau0, mu, sigma: float, lam: float = 0.0):
    """The same model in seconds, for a return of ``mu`` photons in the whole pulse.

    tau0 : (...) s, TDC time of the pulse centre; mu : (...) signal photons
    per shot in the whole pulse; sigma : s, the pulse σ; lam : Hz, the
    pixel's background rate.  Returns ``p, bias, var`` (...): the probability
    of a signal-first detection, E[arrival − τ0] in s and its variance in s².
    """
    a = -np.asarray(tau0, dtype=np.float64) / sigma
    mu_w = np.asarray(mu, dtype=np.float64) * ndtr(-np.maximum(a, -8.0))
    p, mean, var = first_photon_signal(a, mu_w, lam * sigma)
    return p, mean * sigma, var * sigma * sigma


@dataclass(frozen=True, slots=True)
class FirstPhotonTable:
    """:func:`first_photon_moments` tabulated on a grid (:func:`first_photon_table`).

    Attributes
    ----------
    a_grid : (A,) float64, the pulse centre's offset ``a`` from the TDC start, in pulse σ.
    logmu_grid : (M,) float64, log of the signal photons μ_w in the window.
    mean : (A, M) float64, mean first-photon arrival, in pulse σ.
    var : (A, M) float64, its variance, in pulse σ².
    """

    a_grid: np.ndarray
    logmu_grid: np.ndarray
    mean: np.ndarray
    var: np.ndarray


@functools.lru_cache(maxsize=1)
def first_photon_table() -> FirstPhotonTable:
    """:func:`first_photon_moments` on the (a, log μ_w) grid, tabulated once per process
    and kept in the disk cache (:mod:`mems_stereo.util.cache`) across runs."""
    import scipy

    from mems_stereo.util.cache import cached_arrays, source_key

    ag = np.linspace(*_A_GRID)
    lg = np.linspace(*_LOGMU_GRID)

    def compute():
        mean = np.empty((ag.size, lg.size))
        var = np.empty_like(mean)
        for i, a in enumerate(ag):  # row by row: the temporaries stay (n_mu, n_quad)
            mean[i], var[i] = first_photon_moments(a, np.exp(lg))
        return {"mean": mean, "var": var}

    key = source_key(Path(__file__).read_bytes(), scipy.__version__, _A_GRID, _LOGMU_GRID)
    got = cached_arrays("first-photon", key, compute)
    mean, var = got["mean"], got["var"]
    if mean.shape != (ag.size, lg.size) or var.shape != mean.shape:  # a foreign file
        got = compute()
        mean, var = got["mean"], got["var"]
    return FirstPhotonTable(ag, lg, mean, var)


def _table_lookup(a, logmu):
    """Bilinear look-up of (mean, var) on the table; arguments clipped to its grid.

    ``a`` and ``logmu`` broadcast against each other; the arithmetic is done on
    their own shapes (``a`` is usually one value per peak) and the four corners
    are gathered from the flattened tables, so an (Q, 1, 1) ``a`` against a
    (Q, J, B) ``logmu`` costs no (Q, J, B) index arrays for ``a``.
    """
    tab = first_photon_table()
    ag, lg, mean, var = tab.a_grid, tab.logmu_grid, tab.mean, tab.var
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


def detection_log_odds(f):
    """log p − log(1 − p) of a shot with spot share f (…) on the μ0 grid -> (…, J)."""
    kernels = firing_kernels()
    if kernels is not None:  # (compiled: the same numbers)
        f = np.asarray(f, np.float64)
        out = kernels[1](np.ascontiguousarray(f).ravel(), MU_GRID, OUTLIER_PROBABILITY)
        return out.reshape(f.shape + (MU_GRID.size,))
    p = firing_probability(f)
    return np.log(p) - np.log1p(-p)


def firing_probability(f):
    """P(inlier) of a shot with spot share f (…) on the μ0 grid -> (…, J), in (0, 1)."""
    return per_share(_firing, f)


def log_miss_probability(f):
    """ln(1 − P(inlier)) of :func:`firing_probability` (…) -> (…, J)."""
    return per_share(lambda g: np.log1p(-_firing(g)), f)


def band_log_miss(n_band, f_band):
    """(Q, J) ``Σ_b n_b·ln(1 − P(inlier))`` of the (Q, B) valid shots ``n_band`` at spot
    shares ``f_band``: ``np.einsum("qb,qbj->qj", n_band, log_miss_probability(f_band))``,
    the same numbers — that sum runs over b in order from 0, and a step without shots
    adds a zero, so only the steps with shots are evaluated and added in that order."""
    n_band = np.asarray(n_band, np.float64)
    qi, bi = np.nonzero(n_band)
    return band_log_miss_rows(n_band.shape[0], qi, n_band[qi, bi],
                              np.asarray(f_band, np.float64)[qi, bi])


def band_log_miss_rows(Q: int, row, n, f):
    """(Q, J) :func:`band_log_miss` from its nonzero entries: ``row`` (N,) int the
    entry's row (each row's entries in band order), ``n`` (N,) float64 its valid shots
    (not 0) and ``f`` (N,) its spot share; the same sums (each row's entries added in
    order, whatever the other rows)."""
    kernels = firing_kernels()
    if kernels is not None:  # (compiled: the same sums)
        return kernels[0](Q, np.asarray(row, np.int64), np.asarray(n, np.float64),
                          np.asarray(f, np.float64), MU_GRID, OUTLIER_PROBABILITY)
    out = np.zeros((Q, MU_GRID.size))
    if np.size(row):
        np.add.at(out, row, np.asarray(n, np.float64)[:, None]
                  * log_miss_probability(np.asarray(f, np.float64)))
    return out


def _firing(f):
    e = OUTLIER_PROBABILITY
    pf = -np.expm1(-MU_GRID * np.asarray(f, dtype=np.float64)[..., None])
    return np.minimum(e + (1 - e) * pf, 1.0 - 1e-12)


def per_share(func, f):
    """``func`` of the spot shares ``f`` (…) -> (…, J), each share's row its own: the
    shares that are 0 (the padding around a band, steps without shots: most of a short
    frame's) take the row of one 0, the others are computed entry by entry — the same
    numbers as ``func(f)``."""
    f = np.asarray(f, dtype=np.float64)
    zero = f == 0
    if f.ndim == 0 or not np.any(zero):
        return func(f)
    out = np.empty(f.shape + (MU_GRID.size,))
    out[zero] = func(np.zeros(1))[0]
    some = ~zero
    if np.any(some):
        out[some] = func(f[some])
    return out


def _at_shares(func, mu_s, nonzero):
    """``func`` (elementwise) of ``mu_s`` (Q, J, B), evaluated where the spot share
    ``nonzero`` (Q, B) is not 0 and once for the rest (``mu_s`` 0 there): the same
    numbers as ``func(mu_s)``."""
    out = np.full(mu_s.shape, func(np.zeros(1))[0])
    qi, bi = np.nonzero(nonzero)
    if qi.size:
        out[qi, :, bi] = func(mu_s[qi, :, bi])
    return out


def _band_lookup(a, lm, f_band):
    """:func:`_table_lookup` of ``a`` (Q,) against ``lm`` (Q, J, B), the same numbers:
    where the spot share ``f_band`` (Q, B) is 0 (the padding around a band, steps
    without shots), ``lm`` is the grid's floor for every μ0 and the look-up is
    one value per peak, broadcast; the others are looked up entry by entry."""
    zero = f_band == 0
    if not np.any(zero):
        return _table_lookup(a[:, None, None], lm)
    lz = np.log(np.clip(np.zeros(1), 1e-4, MU_MAX))  # lm where μ0·f = 0
    d0, v0 = _table_lookup(a[:, None], lz[None, :])  # (Q, 1)
    d = np.broadcast_to(d0[:, :, None], lm.shape).copy()
    v = np.broadcast_to(v0[:, :, None], lm.shape).copy()
    qi, bi = np.nonzero(~zero)
    if qi.size:
        dd, vv = _table_lookup(a[qi, None], lm[qi, :, bi])  # (N, J)
        d[qi, :, bi] = dd
        v[qi, :, bi] = vv
    return d, v


def _band_sums(f_band, n_band, a):
    """``(dj, vj)`` (Q, J): the band's mean delay for each μ0 of the grid and its
    mixture variance, in pulse σ and σ² (``f_band``, ``n_band`` (Q, B), ``a`` (Q,),
    see :func:`first_photon_delay`); by the compiled kernel where numba is loaded
    (:func:`~mems_stereo.physics.first_photon_kernel.band_moments`: the same numbers)."""
    kernel = band_kernel() if f_band.ndim == 2 and f_band.shape[0] else None
    zero = np.zeros(1)
    if kernel is not None and np.shape(n_band) == f_band.shape:
        qi, bi = np.nonzero(f_band)  # (the transcendental functions only where μ0·f ≠ 0)
        mu_nz = f_band[qi, bi][:, None] * MU_GRID[None, :]
        return band_moments(kernel, f_band, n_band, -np.expm1(-mu_nz),
                            np.log(np.clip(mu_nz, 1e-4, MU_MAX)), a,
                            (-np.expm1(-zero)[0], np.log(np.clip(zero, 1e-4, MU_MAX))[0]),
                            first_photon_table())
    mu_s = MU_GRID[None, :, None] * f_band[:, None, :]  # (Q, J, B)
    nonzero = f_band != 0  # (the transcendental functions only where μ0·f is not 0)
    w = n_band[:, None, :] * _at_shares(lambda m: -np.expm1(-m), mu_s, nonzero)
    w = w / np.maximum(w.sum(axis=2, keepdims=True), 1e-300)  # expected detections per step
    lm = _at_shares(lambda m: np.log(np.clip(m, 1e-4, MU_MAX)), mu_s, nonzero)
    d, v = _band_lookup(a, lm, f_band)
    dj = np.sum(w * d, axis=2)  # (Q, J) mean delay of the band for each μ0
    return dj, np.sum(w * (v + d * d), axis=2) - dj * dj  # and the mixture variance


def first_photon_delay(log_likelihood, f_band, n_band, tau0, sigma, mu_factor=None):
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
    mu_factor : float > 1 or None; with it a fifth result, ``sigma_model``.

    Returns
    -------
    delay : (Q,) s, E[mean arrival − pulse centre] of the detections (the
        average over the band's shots of δ(a, μ0·f_s) weighted by their
        detection probabilities, then over the posterior of μ0).
    sigma_delay : (Q,) s, its posterior standard deviation.
    var_arrival : (Q,) s², E[variance of one detection's arrival] (the
        band's mixture of first-photon spreads).
    mu : (Q,) posterior mean of μ0.
    sigma_model : (Q,) s, only with ``mu_factor`` F: half the change of the band's
        delay between μ0 = μ/F and μ0 = μ·F (linear in log μ0 on the grid, clipped
        to it) — the delay's sensitivity to a signal level the spot model
        misjudges by a factor F, which the posterior's spread (the data's) does not
        hold.
    """
    a = -np.asarray(tau0, dtype=np.float64) / sigma
    dj, vj = _band_sums(np.asarray(f_band, np.float64), n_band, a)
    return posterior_delay(log_likelihood, dj, vj, sigma, mu_factor)


def posterior_delay(log_likelihood, dj, vj, sigma, mu_factor=None):
    """:func:`first_photon_delay` from the band's moments on the μ0 grid: ``dj``, ``vj``
    (Q, J) the band's mean delay and mixture variance for each μ0 of
    :data:`MU_GRID`, in pulse σ and σ²; the other arguments and the results as there."""
    ll = np.asarray(log_likelihood, dtype=np.float64)
    post = np.exp(ll - ll.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)  # (Q, J)
    dm = np.sum(post * dj, axis=1)
    sd = np.sqrt(np.maximum(np.sum(post * dj * dj, axis=1) - dm * dm, 0.0))
    mu = post @ MU_GRID
    out = (dm * sigma, sd * sigma, np.sum(post * vj, axis=1) * sigma ** 2, mu)
    if mu_factor is None:
        return out
    lg = np.log(MU_GRID)
    h = lg[1] - lg[0]
    u = (np.log(np.maximum(mu, MU_GRID[0])) - lg[0]) / h
    du = math.log(mu_factor) / h

    def at(v):  # dj at grid position v (Q,), linear between the grid's points
        v = np.clip(v, 0.0, lg.size - 1.0)
        i = np.minimum(np.floor(v).astype(np.int64), lg.size - 2)
        t = v - i
        r = np.arange(dj.shape[0])
        return (1 - t) * dj[r, i] + t * dj[r, i + 1]

    return out + (0.5 * np.abs(at(u + du) - at(u - du)) * sigma,)


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


def first_photon_mean_truncated(mu, start, pulse: PulseShape) -> np.ndarray:
    """Mean delay (s) of the first return photon given ≥ 1 in the TDC window.

    The window opens at delay ``start`` (s, on the pulse's time axis) and does not
    close: G(s) = (1 − e^(−μ(F(s) − F0))) / (1 − e^(−μ(1 − F0))), F0 = F(start), and
    E = start + ∫_start^∞ (1 − G) ds.  ``mu`` (M,) and ``start`` (T,) give (M, T);
    without truncation (start below the pulse) it is :func:`first_photon_mean_delay`.
    """
    m = np.asarray(mu, dtype=np.float64).reshape(-1, 1, 1)
    s0 = np.asarray(start, dtype=np.float64).reshape(1, -1, 1)
    t, F = pulse.t[None, None, :], pulse.cdf[None, None, :]
    F0 = pulse.cdf_at(s0)
    inside = t >= s0
    num = -np.expm1(-m * np.clip(F - F0, 0.0, None))
    den = -np.expm1(-m * (1.0 - F0))
    with np.errstate(invalid="ignore", divide="ignore"):
        G = np.where(inside, num / den, 0.0)
    G = np.where(den > 0, G, 1.0)
    lo = np.maximum(s0[..., 0], pulse.t[0])  # below the grid G is 0: 1 − G integrates to it
    return lo + np.trapezoid(np.where(inside, 1.0 - G, 0.0), pulse.t, axis=-1)


class ShapeExcess:
    """First-photon mean delay of ``pulse`` less that of a Gaussian of the same σ, s.

    Both are measured from their pulse's mean delay, so the excess is 0 for μ → 0
    without truncation; it is what a non-Gaussian pulse (``docs/hardware.md``) adds
    to the Gaussian model's pile-up delay (:func:`first_photon_delay`) at μ signal
    photons per shot.  Tabulated once on ``n_grid`` log-spaced μ in [1e-3,
    :data:`MU_MAX`] and 33 TDC openings from −8σ to +2σ relative to the pulse's
    mean (:func:`first_photon_mean_truncated`), then interpolated (below 1e-3 the
    excess goes linearly in μ to its μ → 0 value).
    """

    def __init__(self, pulse: PulseShape, sigma: float, n_grid: int = 49):
        from scipy.interpolate import RegularGridInterpolator

        self.grid = np.geomspace(1e-3, MU_MAX, n_grid)
        self.starts = np.linspace(-8 * sigma, 2 * sigma, 33)
        gauss = PulseShape.gaussian(sigma * FWHM_PER_SIGMA)
        mean = pulse.t[-1] - np.trapezoid(pulse.cdf, pulse.t)
        mus = np.concatenate([[1e-9], self.grid])
        ex = (first_photon_mean_truncated(mus, self.starts + mean, pulse) - mean
              - first_photon_mean_truncated(mus, self.starts, gauss))
        self.ex0 = ex[0]
        self.table = RegularGridInterpolator((np.log(self.grid), self.starts), ex[1:])

    def __call__(self, mu, start=None) -> np.ndarray:
        """Excess (s) at ``mu`` photons with the window opening at ``start`` (s
        relative to the pulse's mean, −τ0; None: far before the pulse), broadcast;
        NaN where either is NaN."""
        m = np.asarray(mu, dtype=np.float64)
        st = self.starts[0] if start is None else start
        s0 = np.broadcast_to(np.asarray(st, np.float64), np.broadcast(m, st).shape)
        m = np.broadcast_to(m, s0.shape)
        sc = np.clip(s0, self.starts[0], self.starts[-1])
        lm = np.log(np.clip(np.nan_to_num(m, nan=1.0), self.grid[0], self.grid[-1]))
        at = self.table(np.stack([lm, np.nan_to_num(sc)], -1))
        base = np.interp(sc, self.starts, self.ex0)
        small = np.clip(m / self.grid[0], 0.0, 1.0)
        out = np.where(small < 1, base + (at - base) * small, at)
        return np.where(np.isfinite(m) & np.isfinite(s0), out, np.nan)


def shape_delay_excess(mu, pulse: PulseShape, sigma: float, start=None) -> np.ndarray:
    """:class:`ShapeExcess` of ``pulse`` and σ evaluated once at ``mu``, ``start``."""
    return ShapeExcess(pulse, sigma)(mu, start)
