"""The band sums of the first-photon delay, loop by loop (a numba kernel).

:func:`~mems_stereo.physics.first_photon.first_photon_delay` weighs each step of a
peak's band by its expected detections and averages the tabulated first-photon
moments over them, for every μ0 of the grid: (Q, J, B) temporaries of which most
entries are the padding around a band (steps without shots, spot share 0).
:func:`band_moments` computes the same (Q, J) sums with the compiled
:func:`_band_moments_py`: the transcendental functions stay NumPy's (evaluated by the
caller at the nonzero shares only), the kernel does the rest of the arithmetic in
NumPy's order — the bilinear look-up's products and sums as written, each sum over
the band in NumPy's pairwise order (:func:`~mems_stereo.physics.background.pairwise_plan`):
the same numbers.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.physics.background import pairwise_plan, pairwise_sum_py
from mems_stereo.util.lazy_numba import compiled_kernel


def band_kernel():
    """The compiled :func:`_band_moments_py` where numba is imported already (the
    frames and dense runs load it), else None: the caller then uses NumPy."""
    import sys

    if "numba" not in sys.modules:
        return None
    return compiled_kernel(_band_moments_py, {"_pairwise": pairwise_sum_py,
                                              "_lookup": _lookup})


def band_moments(kernel, f_band, n_band, ex, lm, a, zero_values, table):
    """``(dj, vj)`` (Q, J) float64 of :func:`first_photon_delay` by ``kernel``
    (:func:`band_kernel`).

    f_band, n_band : (Q, B) spot shares and valid shots; ex, lm : (N, J) float64,
    ``1 − exp(−μ0 f)`` and the clipped ``ln(μ0 f)`` at the N nonzero shares (in the
    order of ``np.nonzero(f_band)``); a : (Q,) the TDC start in pulse σ;
    zero_values : ``(ex, lm)`` at a share of 0; table : the
    :class:`~mems_stereo.physics.first_photon.FirstPhotonTable`."""
    ag, lg = table.a_grid, table.logmu_grid
    grid = np.array([ag[0], ag[1] - ag[0], ag.size - 1.000001,
                     lg[0], lg[1] - lg[0], lg.size - 1.000001])
    return kernel(np.ascontiguousarray(f_band, np.float64),
                  np.ascontiguousarray(n_band, np.float64),
                  np.ascontiguousarray(ex), np.ascontiguousarray(lm),
                  np.ascontiguousarray(a, np.float64), float(zero_values[0]),
                  float(zero_values[1]), table.mean.ravel(), table.var.ravel(), grid,
                  lg.size, pairwise_plan(f_band.shape[1]))


def _band_moments_py(f_band, n_band, ex, lm, a, ex0, lm0, mean_t, var_t, grid, n_mu,
                     plan):  # pragma: no cover - compiled by numba
    """Per peak q and grid μ0 j: the weights ``w = n·ex / max(Σ_b n·ex, 1e-300)``, the
    look-up ``(d, v)`` of ``(a_q, lm)`` (bilinear, as ``_table_lookup``), then
    ``dj = Σ_b w·d`` and ``vj = Σ_b w·(v + d·d) − dj·dj``; sums in NumPy's pairwise
    order over the whole band (``plan``)."""
    Q, B = f_band.shape
    J = ex.shape[1]
    dj = np.empty((Q, J))
    vj = np.empty((Q, J))
    w = np.empty((J, B))
    d = np.empty((J, B))
    v = np.empty((J, B))
    row = np.empty(B)
    k = 0  # the next nonzero share
    for q in range(Q):
        fa = min(max((a[q] - grid[0]) / grid[1], 0.0), grid[2])
        i = np.int64(fa)
        wa = fa - i
        d0, v0 = _lookup(wa, i, lm0, grid, n_mu, mean_t, var_t)
        for b in range(B):
            nb = n_band[q, b]
            if f_band[q, b] != 0:
                for j in range(J):
                    w[j, b] = nb * ex[k, j]
                    d[j, b], v[j, b] = _lookup(wa, i, lm[k, j], grid, n_mu, mean_t, var_t)
                k += 1
            else:
                for j in range(J):
                    w[j, b] = nb * ex0
                    d[j, b] = d0
                    v[j, b] = v0
        for j in range(J):
            s = _pairwise(w[j], plan)
            den = s if (s >= 1e-300 or s != s) else 1e-300
            for b in range(B):
                w[j, b] = w[j, b] / den
                row[b] = w[j, b] * d[j, b]
            m = _pairwise(row, plan)
            dj[q, j] = m
            for b in range(B):
                row[b] = w[j, b] * (v[j, b] + d[j, b] * d[j, b])
            vj[q, j] = _pairwise(row, plan) - m * m
    return dj, vj


_pairwise = pairwise_sum_py  # (the kernel's helper; rebound to its compiled form)


def _lookup(wa, i, lm, grid, n_mu, mean_t, var_t):  # pragma: no cover - compiled by numba
    """The bilinear look-up of ``_table_lookup`` at one ``(a, lm)``: ``wa``, ``i`` the
    a-axis weight and index; returns (mean, var)."""
    fm = min(max((lm - grid[3]) / grid[4], 0.0), grid[5])
    jm = np.int64(fm)
    wm = fm - jm
    k00 = i * n_mu + jm
    c00, c10, c01, c11 = (1 - wa) * (1 - wm), wa * (1 - wm), (1 - wa) * wm, wa * wm
    dv = (c00 * mean_t[k00] + c10 * mean_t[k00 + n_mu] + c01 * mean_t[k00 + 1]
          + c11 * mean_t[k00 + n_mu + 1])
    vv = (c00 * var_t[k00] + c10 * var_t[k00 + n_mu] + c01 * var_t[k00 + 1]
          + c11 * var_t[k00 + n_mu + 1])
    return dv, vv
