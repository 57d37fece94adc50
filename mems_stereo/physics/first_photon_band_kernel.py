"""The first-photon correction's per-peak loops of a frame, compiled (numba).

A peak's first-photon correction reads the steps around its inlier band: the valid
shots ``n`` and the spot's share ``f`` of the pixel at each.  NumPy evaluates it as
chains of small-array operations per block of peaks; here every peak's band is one
loop over its entries, laid end to end (row by row, each row's entries in band order:
the flat layout of
:func:`~mems_stereo.pipeline.first_photon_correction.block_band_steps`):

* :func:`band_likelihood_moments` — on the μ0 grid (:data:`~.first_photon.MU_GRID`),
  the band's log-probability of its misses ``Σ n·ln(1 − P(inlier))``
  (:func:`~.first_photon.band_log_miss`) and the band's first-photon moments (the
  mean delay and mixture variance of :func:`~.first_photon.first_photon_delay`'s band
  sums), with one ``expm1`` per (entry, μ0) shared by both;
* :func:`band_figures` — given each peak's posterior μ0, the mean angle's expected
  bias (:func:`~mems_stereo.pipeline.first_photon_correction.mean_angle_bias`), its
  binomial factor
  (:func:`~mems_stereo.pipeline.first_photon_correction.angle_binomial_factor`) and
  the firings the model predicts at the grid's top
  (:func:`~mems_stereo.pipeline.first_photon_correction._beyond_model`);
* :func:`log_odds` — the log-odds of a shot's firing
  (:func:`~.first_photon.detection_log_odds`) for the frames' likelihood.

The numbers are NumPy's but for the order of the sums (sequential here, pairwise
there), the divisions of the weighted means (one per sum here, per term there) and
``ln(1 − P)`` in closed form where NumPy's rounded form is within 2.5e-13 of it
(:data:`CLOSED_BELOW`).  ``math.expm1``, ``log`` and ``log1p`` are the C
library's, as NumPy's float64 functions are on CPUs without its vectorised forms.
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.physics.first_photon import MU_MAX
from mems_stereo.physics.first_photon_kernel import table_lookup_one
from mems_stereo.util.lazy_numba import compiled_kernel

#: μ0·f up to which ``ln(1 − P)`` is taken in closed form, ``ln(1 − e) − μ0·f``, rather
#: than as NumPy's ``log1p(−P)`` of the rounded P: there P ≤ 1 − 0.98·e⁻⁷, and
#: NumPy's form is off the exact value by at most 2.2e-16 / (1 − P) ≈ 2.5e-13 (P's
#: rounding); above it, where P nears 1, the rounding of P dominates 1 − P and NumPy's
#: form is kept (the outputs stay within 1e-9 of NumPy's)
CLOSED_BELOW = 7.0


def kernels():
    """``(likelihood_moments, figures)``: the compiled :func:`_likelihood_moments_py`
    and :func:`_figures_py` (numba's disk cache), or None without numba."""
    a = compiled_kernel(_likelihood_moments_py, {"_lookup": table_lookup_one})
    return None if a is None else (a, compiled_kernel(_figures_py),
                                   compiled_kernel(_log_odds_py))


def log_odds(kernel, f, mu_grid, outlier: float) -> np.ndarray:
    """(N, J) float64 ``ln P − ln(1 − P)`` of a shot at spot share ``f`` (N,) on the μ0
    grid (:func:`~mems_stereo.physics.first_photon.detection_log_odds`, with
    ``ln(1 − P)`` in closed form up to :data:`CLOSED_BELOW`)."""
    return kernel(np.ascontiguousarray(f, np.float64).ravel(),
                  np.ascontiguousarray(mu_grid, np.float64), float(outlier))


def _log_odds_py(f, mu, e):  # pragma: no cover - compiled by numba
    """:func:`log_odds`' loop."""
    out = np.empty((f.size, mu.size))
    log_e = math.log1p(-e)
    for t in range(f.size):
        for j in range(mu.size):
            x = mu[j] * f[t]
            p = min(e + (1 - e) * -math.expm1(-x), 1.0 - 1e-12)
            out[t, j] = math.log(p) - (log_e - x if x <= CLOSED_BELOW else math.log1p(-p))
    return out


def band_likelihood_moments(kernel, starts, n, f, mu_grid, outlier: float, a, table):
    """``(log_miss, dj, vj)``, each (R, J) float64, of R bands laid end to end.

    starts : (R + 1,) int64, row r's entries are ``starts[r]:starts[r + 1]``.
    n, f : (N,) float64 valid shots and spot shares of the entries (n 0: not counted).
    mu_grid : (J,) the μ0 grid; outlier : the probability of an unexplained inlier.
    a : (R,) float64, each peak's TDC start in pulse σ (``−τ0/σ``).
    table : the :class:`~mems_stereo.physics.first_photon.FirstPhotonTable`.

    ``log_miss[r, j] = Σ n·ln(1 − P)`` with ``P = min(e + (1 − e)(1 − exp(−μ_j f)),
    1 − 10⁻¹²)`` over the entries with shots (``ln(1 − e) − μ_j f`` up to
    :data:`CLOSED_BELOW`); ``dj``, ``vj`` the band's mean delay and
    mixture variance (pulse σ, σ²) of μ0 = μ_j: the entries with shots and spot weighed
    by ``w = n·(1 − exp(−μ_j f))``, the table's moments ``(d, v)`` at ``(a, ln μ_j f)``,
    ``dj = Σ w·d / Σ w``, ``vj = Σ w·(v + d²) / Σ w − dj²`` (Σ w at least 10⁻³⁰⁰: 0
    and 0 without such an entry); ``ln μ_j f`` as ``ln μ_j + ln f`` (one logarithm
    per entry; NumPy's ``ln(μ_j·f)`` differs in the last place), clipped to
    [ln 10⁻⁴, ln MU_MAX] as there."""
    ag, lg = table.a_grid, table.logmu_grid
    grid = np.array([ag[0], ag[1] - ag[0], ag.size - 1.000001,
                     lg[0], lg[1] - lg[0], lg.size - 1.000001, MU_MAX])
    return kernel(np.asarray(starts, np.int64), np.ascontiguousarray(n, np.float64),
                  np.ascontiguousarray(f, np.float64),
                  np.ascontiguousarray(mu_grid, np.float64), float(outlier),
                  np.ascontiguousarray(a, np.float64), table.mean.ravel(),
                  table.var.ravel(), grid, lg.size)


def _likelihood_moments_py(starts, n, f, mu, e, a, mean_t, var_t, grid,
                           n_mu):  # pragma: no cover - compiled by numba
    """:func:`band_likelihood_moments`'s loop (arguments as there, the table flat)."""
    R = starts.size - 1
    J = mu.size
    log_miss = np.zeros((R, J))
    dj = np.zeros((R, J))
    vj = np.zeros((R, J))
    sw = np.empty(J)
    swd = np.empty(J)
    swv = np.empty(J)
    log_mu = np.log(mu)
    lm_lo, lm_hi = math.log(1e-4), math.log(grid[6])
    log_e = math.log1p(-e)
    for r in range(R):
        fa = min(max((a[r] - grid[0]) / grid[1], 0.0), grid[2])
        i = np.int64(fa)
        wa = fa - i
        for j in range(J):
            sw[j] = 0.0
            swd[j] = 0.0
            swv[j] = 0.0
        for t in range(starts[r], starts[r + 1]):
            nt = n[t]
            if nt == 0:
                continue
            ft = f[t]
            log_f = math.log(ft) if ft > 0 else -math.inf
            for j in range(J):
                x = mu[j] * ft
                ex = -math.expm1(-x)
                if x <= CLOSED_BELOW:  # ln(1 − P) = ln(1 − e) − μ0·f
                    log_miss[r, j] += nt * (log_e - x)
                else:
                    p = min(e + (1 - e) * ex, 1.0 - 1e-12)
                    log_miss[r, j] += nt * math.log1p(-p)
                if ft != 0:
                    w = nt * ex
                    lm = min(max(log_mu[j] + log_f, lm_lo), lm_hi)
                    d, v = _lookup(wa, i, lm, grid, n_mu, mean_t, var_t)
                    sw[j] += w
                    swd[j] += w * d
                    swv[j] += w * (v + d * d)
        for j in range(J):
            den = max(sw[j], 1e-300)
            m = swd[j] / den
            dj[r, j] = m
            vj[r, j] = swv[j] / den - m * m
    return log_miss, dj, vj


def band_figures(kernel, starts, steps, n, f_band, f_full, mu, theta_bar, top_mu: float,
                 min_shots: float):
    """``(bias, binomial, k_top)``, each (R,) float64, of R bands laid end to end
    (``starts``, as :func:`band_likelihood_moments`; ``steps``, ``n``, ``f_band``,
    ``f_full`` (N,) the entries' steps, valid shots, spot share where shots count and
    spot share everywhere in the band) at each peak's μ0 ``mu`` (R,):

    bias : steps, ``Σ n·p·s / Σ n·p − Σ p_f·s / Σ p_f`` (``p = 1 − exp(−μ0·f_band)``,
        ``p_f`` the same of ``f_full``), 0 where not finite;
    binomial : ``Σ n·p·(1 − p)·(s − θ̄)² / Σ n·p·(s − θ̄)²`` clipped to [0, 1] where
        finite and the band's steps with shots hold at least ``min_shots`` on average
        (``theta_bar`` (R,) the mean angle in steps), else 1;
    k_top : ``Σ n·(1 − exp(−top_mu·f_band))``, the firings at μ0 = ``top_mu``.
    """
    return kernel(np.asarray(starts, np.int64), np.ascontiguousarray(steps, np.float64),
                  np.ascontiguousarray(n, np.float64),
                  np.ascontiguousarray(f_band, np.float64),
                  np.ascontiguousarray(f_full, np.float64),
                  np.ascontiguousarray(mu, np.float64),
                  np.ascontiguousarray(theta_bar, np.float64), float(top_mu),
                  float(min_shots))


def _figures_py(starts, steps, n, f_band, f_full, mu, theta_bar, top_mu,
                min_shots):  # pragma: no cover - compiled by numba
    """:func:`band_figures`'s loop (arguments as there)."""
    R = starts.size - 1
    bias = np.zeros(R)
    binom = np.ones(R)
    k_top = np.zeros(R)
    for r in range(R):
        m = mu[r]
        tb = theta_bar[r]
        swn = 0.0
        sws = 0.0
        spf = 0.0
        spfs = 0.0
        sb_num = 0.0
        sb_den = 0.0
        n_sum = 0.0
        n_pos = 0
        top = 0.0
        for t in range(starts[r], starts[r + 1]):
            s, nt = steps[t], n[t]
            pf = -math.expm1(-m * f_full[t])
            spf += pf
            spfs += pf * s
            if nt != 0:
                p = -math.expm1(-m * f_band[t])
                w = nt * p
                swn += w
                sws += w * s
                dev2 = (s - tb) * (s - tb)
                sb_den += w * dev2
                sb_num += w * dev2 * (1.0 - p)
                n_sum += nt
                n_pos += 1
                top += nt * -math.expm1(-top_mu * f_band[t])
        b = sws / swn - spfs / spf if (swn != 0 and spf != 0) else math.nan
        bias[r] = b if math.isfinite(b) else 0.0
        k_top[r] = top
        if n_pos > 0 and n_sum / n_pos >= min_shots and sb_den != 0:
            q = sb_num / sb_den
            if math.isfinite(q):
                binom[r] = min(max(q, 0.0), 1.0)
    return bias, binom, k_top


#: the name :func:`_likelihood_moments_py` calls the look-up by (bound to its compiled
#: form when it compiles)
_lookup = table_lookup_one
