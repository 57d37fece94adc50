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

import math

import numpy as np

from mems_stereo.physics.background import pairwise_plan
from mems_stereo.util.lazy_numba import compiled_kernel


def band_kernel():
    """The compiled :func:`_band_moments_py` where numba is imported already (the
    frames and dense runs load it), else None: the caller then uses NumPy."""
    import sys

    if "numba" not in sys.modules:
        return None
    return compiled_kernel(_band_moments_py, {"_lookup": table_lookup_one,
                                              "_peak_sums": _peak_sums,
                                              "_sparse_pairwise": _sparse_pairwise})


def firing_kernels():
    """``(log_miss, log_odds)``: the compiled :func:`_log_miss_rows_py` and
    :func:`_log_odds_py` where numba is imported already, else None (the caller then
    uses NumPy).  Their ``expm1``, ``log`` and ``log1p`` are the C library's, as
    NumPy's float64 functions are on CPUs where NumPy has no vectorised forms of them
    (as on this project's machines: the same bits; elsewhere within a unit in the
    last place)."""
    import sys

    if "numba" not in sys.modules:
        return None
    return compiled_kernel(_log_miss_rows_py), compiled_kernel(_log_odds_py)


def _log_miss_rows_py(Q, row, n, f, mu, e):  # pragma: no cover - compiled by numba
    """(Q, J) ``Σ n·ln(1 − P(inlier))`` of the entries (``row``, ``n``, ``f`` (N,)) on
    the μ0 grid ``mu`` (J,), each row's entries added in order (``np.add.at``'s)."""
    out = np.zeros((Q, mu.size))
    for t in range(row.size):
        for j in range(mu.size):
            p = min(e + (1 - e) * -math.expm1(-mu[j] * f[t]), 1.0 - 1e-12)
            out[row[t], j] += n[t] * math.log1p(-p)
    return out


def _log_odds_py(f, mu, e):  # pragma: no cover - compiled by numba
    """(N, J) ``ln p − ln(1 − p)`` of P(inlier) at the shares ``f`` (N,) on ``mu``."""
    out = np.empty((f.size, mu.size))
    for t in range(f.size):
        for j in range(mu.size):
            p = min(e + (1 - e) * -math.expm1(-mu[j] * f[t]), 1.0 - 1e-12)
            out[t, j] = math.log(p) - math.log1p(-p)
    return out


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
    order over the whole band (``plan``).  The terms are 0 at the steps without shots
    or spot (most of a frame's band): a peak's sums run over its other steps alone
    (:func:`_sparse_pairwise`: the same numbers), or over every step where a sum would
    hold no nonzero term (the sign of its zeros then decides)."""
    Q, B = f_band.shape
    J = ex.shape[1]
    out = np.empty((2, Q, J))
    w = np.empty((J, B))
    d = np.empty((J, B))
    v = np.empty((J, B))
    row = np.empty((2, B))
    pos = np.empty(B, np.int64)
    kpos = np.empty(B, np.int64)
    work = np.empty(8 + plan.shape[0])  # the pairwise sums' lanes and stack
    k = 0  # the next nonzero share
    for q in range(Q):
        fa = min(max((a[q] - grid[0]) / grid[1], 0.0), grid[2])
        i = np.int64(fa)
        wa = fa - i
        npos = 0
        k_q = k
        for b in range(B):
            if f_band[q, b] != 0:
                if n_band[q, b] != 0:
                    pos[npos] = b
                    kpos[npos] = k
                    npos += 1
                k += 1
        ok = npos > 0
        if ok:  # the terms at the steps with shots and spot, in pos order
            for t in range(npos):
                nb = n_band[q, pos[t]]
                for j in range(J):
                    w[j, t] = nb * ex[kpos[t], j]
                    d[j, t], v[j, t] = _lookup(wa, i, lm[kpos[t], j], grid, n_mu, mean_t,
                                               var_t)
            ok = _peak_sums(w, d, v, row, pos, npos, plan, work, out, q)
        if not ok:  # every step
            d0, v0 = _lookup(wa, i, lm0, grid, n_mu, mean_t, var_t)
            kk = k_q
            for b in range(B):
                nb = n_band[q, b]
                if f_band[q, b] != 0:
                    for j in range(J):
                        w[j, b] = nb * ex[kk, j]
                        d[j, b], v[j, b] = _lookup(wa, i, lm[kk, j], grid, n_mu, mean_t,
                                                   var_t)
                    kk += 1
                else:
                    for j in range(J):
                        w[j, b] = nb * ex0
                        d[j, b] = d0
                        v[j, b] = v0
            for t in range(B):
                pos[t] = t
            _peak_sums(w, d, v, row, pos, B, plan, work, out, q)
    return out[0], out[1]


def _peak_sums(w, d, v, row, pos, npos, plan, work, out, q):  # pragma: no cover
    """One peak's ``dj``, ``vj`` into ``out[:, q]`` from its terms at the steps
    ``pos[:npos]`` (the others 0); False (nothing written) where a sum would hold no
    nonzero term and ``npos`` is not every step."""
    J = w.shape[0]
    every = npos == w.shape[1] and pos[npos - 1] == npos - 1
    for j in range(J):
        s, nz = _sparse_pairwise(w[j], pos, npos, plan, work)
        if not (nz or every):
            return False
        den = s if (s >= 1e-300 or s != s) else 1e-300
        for t in range(npos):
            w[j, t] = w[j, t] / den
            row[0, t] = w[j, t] * d[j, t]
            row[1, t] = w[j, t] * (v[j, t] + d[j, t] * d[j, t])
        m, nz1 = _sparse_pairwise(row[0], pos, npos, plan, work)
        m2, nz2 = _sparse_pairwise(row[1], pos, npos, plan, work)
        if not ((nz1 and nz2) or every):
            return False
        out[0, q, j] = m
        out[1, q, j] = m2 - m * m
    return True


def _sparse_pairwise(vals, pos, npos, plan, work):  # pragma: no cover - numba
    """``(Σ a, any nonzero)``: the sum of a vector ``a`` that is ``vals[t]`` at ``pos[t]``
    (t < npos, increasing) and 0 elsewhere, in NumPy's pairwise order (``plan`` of
    :func:`~mems_stereo.physics.background.pairwise_plan`, as the moving sums' kernels
    add), adding the terms at
    ``pos`` alone: a zero added to a sum that holds a nonzero term changes no bit (nor
    does its sign), so with a nonzero term this is the whole vector's sum."""
    r, stack = work[:8], work[8:]  # the lanes of a block, the stack of block sums
    top = 0
    t = 0
    nz = False
    for p in range(plan.shape[0]):
        if plan[p, 0] == 1:
            top -= 1
            stack[top - 1] = stack[top - 1] + stack[top]
            continue
        lo, m = plan[p, 1], plan[p, 2]
        hi = lo + m
        if m < 8:
            res = -0.0
            while t < npos and pos[t] < hi:
                nz = nz or vals[t] != 0
                res += vals[t]
                t += 1
        else:
            for e in range(8):
                r[e] = -0.0
            ub = hi - m % 8
            while t < npos and pos[t] < ub:
                nz = nz or vals[t] != 0
                r[(pos[t] - lo) % 8] += vals[t]
                t += 1
            res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
            while t < npos and pos[t] < hi:
                nz = nz or vals[t] != 0
                res += vals[t]
                t += 1
        stack[top] = res
        top += 1
    return 0.0 + stack[0], nz


def table_lookup_one(wa, i, lm, grid, n_mu, mean_t,
                     var_t):  # pragma: no cover - compiled by numba
    """The bilinear look-up of ``_table_lookup`` at one ``(a, lm)``: ``wa``, ``i`` the
    a-axis weight and index, ``grid`` ``(a0, da, a_top, lm0, dlm, lm_top, …)``, the
    tables flat with ``n_mu`` columns; returns (mean, var)."""
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


#: the name the kernels call the look-up by (bound to its compiled form when they compile)
_lookup = table_lookup_one
