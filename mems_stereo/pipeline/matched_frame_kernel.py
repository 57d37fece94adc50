"""A frame's whole matched-filter box search in one compiled call (:func:`frame_search`).

:func:`~mems_stereo.pipeline.matched.score_candidates` searches, per candidate, the
first stage's window and then (where that finds no passing box) the whole scan band:
:meth:`~mems_stereo.pipeline.matched._CandidateSearch.search` sets up the candidate's
grid (its accepted codes per step, its counted entries, the code range, the table of
powers of ``1 − h``), :class:`~mems_stereo.pipeline.matched_best_kernel.BestBoxGrid`
runs the windows of the search in one kernel call and SciPy's ``pdtrc`` chooses the
box (:func:`~mems_stereo.pipeline.matched_best_kernel.choose_box`).  A floodlight frame
has a few hundred such searches, and their NumPy set-up, the SciPy calls and the
scan p-values cost more than the windows' arithmetic.  Here one compiled call does all
of a frame's candidates:

* the set-up loop by loop (the same integers; the powers by the C library's ``exp``,
  which is NumPy's float64 ``exp`` on CPUs without AVX-512, as here: the same bits);
* the same windows (:func:`~mems_stereo.pipeline.matched_best_kernel.best_kernel_py`'s
  search, :func:`window_py`) with the same sums: the background's running sums in
  the same order (so that boxes tied but for rounding, as a box sliding along steps
  where the frame's scan repeats itself, rank as they did), but summed only as far as
  a box reaching ``min_counts`` reads them, the counts' running sums in integers;
* the choice with SciPy's own ``pdtrc`` (its C function from
  ``scipy.special.cython_special``, called from the compiled code: the same numbers),
  evaluated once per distinct (count, background) pair, and only at the boxes that
  may hold the smallest tail (:func:`_rows_py`): the first smallest is the same box.

A candidate the kernel cannot take as the NumPy path would (no cell in its code range,
a tail that is NaN or none below 1: :func:`~mems_stereo.pipeline.matched_best_kernel.choose_box`'s
fallbacks) is marked :data:`FALLBACK` and searched by the NumPy path.
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.pipeline.matched_best_kernel import step_intervals_py, window_query_py
from mems_stereo.pipeline.matched_boxes import COARSE_TOP, DEVIANCE_MARGIN
from mems_stereo.pipeline.matched_grid import WINDOW_HELPERS
from mems_stereo.util.lazy_numba import compiled_kernel

#: columns of :func:`frame_kernel_py`'s result per candidate
STATUS, STEP, CODE, COUNT, BACKGROUND, P, LEVEL, CODE_POS = range(8)
#: a candidate's status: no box, a box, searched by the NumPy path instead
NO_BOX, BOX, FALLBACK = 0, 1, 2
#: columns of a candidate's integer inputs: its entries' first and end index, its pixel,
#: the first stage's window and its whole scan (steps)
START, END, PIXEL, LOCAL_LO, LOCAL_HI, STEP_LO, STEP_HI = range(7)
#: boxes of one count whose background is within this (relative) of the smallest are
#: near ties: their tails are all evaluated (SciPy's tail is good to ~1e-13 relative)
NEAR_TIE = 1e-9
#: a count whose smallest background is within this share of it keeps all its boxes
#: (where the deviance hardly varies with the background)
DEGENERATE = 1e-3
#: the symbol SciPy's ``pdtrc`` is linked under in the compiled code
PDTRC_SYMBOL = "mems_stereo_scipy_pdtrc"


def _pdtrc_py(k, m):  # pragma: no cover - replaced by SciPy's C function (scipy_pdtrc)
    """SciPy's ``pdtrc(k, m)`` (the compiled kernels call its C function)."""
    from scipy.special import pdtrc

    return float(pdtrc(k, m))


def scipy_pdtrc():
    """SciPy's ``pdtrc`` (double, double) -> double as a numba external function: its C
    function from ``scipy.special.cython_special``, linked under :data:`PDTRC_SYMBOL`
    (before a kernel that calls it is compiled or loaded from numba's cache)."""
    import llvmlite.binding as ll
    from numba import types
    from numba.extending import get_cython_function_address

    ll.add_symbol(PDTRC_SYMBOL, get_cython_function_address("scipy.special.cython_special",
                                                            "pdtrc"))
    return types.ExternalFunction(PDTRC_SYMBOL, types.float64(types.float64, types.float64))


def choose_py(rows, res):  # pragma: no cover - numba
    """:func:`~mems_stereo.pipeline.matched_best_kernel.choose_box` of :func:`best_rows_py`'s
    ``rows`` (K, 4): the first box of smallest tail ``pdtrc(max(N − 1, 0), max(B,
    1e-12))`` (SciPy's), written to ``res`` (p, step, cell, count, background); the
    tail computed once per distinct (count, background).  Returns NO_BOX (no row),
    BOX, or FALLBACK (a NaN, no tail below 1: choose_box's fallbacks)."""
    if rows.shape[0] == 0:
        return NO_BOX
    seen = {(0.5, 0.5): 0.0}  # (a typed dict; no box has a count of 0.5)
    best, bi = np.inf, -1
    for t in range(rows.shape[0]):
        n, b = rows[t, 2], rows[t, 3]
        if n != n or b != b:
            return FALLBACK
        if (n, b) in seen:
            continue  # the same tail as an earlier box: not smaller
        p = _pdtrc(max(n - 1.0, 0.0), max(b, 1e-12))
        if p != p:
            return FALLBACK
        seen[(n, b)] = p
        if p < best:
            best, bi = p, t
    if not best < 1.0:
        return FALLBACK
    res[0] = best
    res[1], res[2], res[3], res[4] = rows[bi, 0], rows[bi, 1], rows[bi, 2], rows[bi, 3]
    return BOX


def window_py(ds, dc, cnt, lo, hi, nps, powers, q, min_counts):  # pragma: no cover - numba
    """One window of the search, as :func:`~mems_stereo.pipeline.matched_grid.window_kernel_py`
    (``q`` its 16 parameters) makes it: returns the row and column (2, K) int64 of its
    valid boxes in the window's (n, m) grid of steps or blocks × cells or blocks, in
    row-major order, their counts and backgrounds (2, K) float64 and m.

    The counts come from the window's 2-D running sums of whole numbers (int64: exact),
    first, so that the background is summed only as far as a box reaching
    ``min_counts`` reads it; the background of each row of blocks is that kernel's
    (``_background_rows_py``) added into its running sums (``_running_sums_py``) as it
    is made, over the rows that hold background only (a row of +0.0 adds nothing), and
    a box's background is the same difference of the running sums at its corners
    (``_box_at_py``): the same bits."""
    j0, j1, k0, k1, fs, fc, h, w = q[0], q[1], q[2], q[3], q[4], q[5], q[6], q[7]
    n, m = (j1 - j0 + fs - 1) // fs, (k1 - k0 + fc - 1) // fc
    D = _count_sums(ds, dc, cnt, q, n, m)
    ri, ci = np.empty(n + h, np.int64), np.empty(m + w, np.int64)
    for i in range(n + h):
        ri[i] = 0 if i < h // 2 + 1 else min(i - h // 2 - 1, n - 1) + 1
    for j in range(m + w):
        ci[j] = 0 if j < w // 2 + 1 else min(j - w // 2 - 1, m - 1) + 1
    half, hc = h // 2, w // 2
    c0 = 0 if q[8] != 0 else hc
    c1 = m if q[9] != 0 else max(0, m - hc)
    n_pos = max(0, n - 2 * half) * max(0, c1 - c0)
    ij, vals, k = np.empty((2, n_pos), np.int64), np.empty((2, n_pos)), 0
    last_r, last_c = 0, 0  # the running sums' last row and column a box reads
    for i in range(half, n - half):
        a, b = ri[i], ri[i + h]
        if D[b, m] - D[a, m] < min_counts:
            continue  # no box of the row holds min_counts
        for j in range(c0, c1):
            x, y = ci[j], ci[j + w]
            v = D[b, y] - D[a, y] - D[b, x] + D[a, x]
            if v >= min_counts:
                ij[0, k], ij[1, k], vals[0, k] = i, j, v
                last_r, last_c = max(last_r, b), max(last_c, y)
                k += 1
    if k == 0:
        return ij[:, :0], vals[:, :0], m
    C, R = _background_sums(lo, hi, nps, powers, q, last_r, last_c)
    kept = 0
    for t in range(k):
        i, j = ij[0, t], ij[1, t]
        ra, rb, x, y = R[ri[i]], R[ri[i + h]], ci[j], ci[j + w]
        bg = C[rb, y] - C[ra, y] - C[rb, x] + C[ra, x]
        if vals[0, t] > bg:
            ij[0, kept], ij[1, kept], vals[0, kept], vals[1, kept] = i, j, vals[0, t], bg
            kept += 1
    return ij[:, :kept], vals[:, :kept], m


def _count_sums_py(ds, dc, cnt, q, n, m):  # pragma: no cover - numba
    """(n + 1, m + 1) int64 2-D running sums (a leading row and column of 0) of the
    counts of the window ``q`` (j0, j1, k0, k1, fs, fc, …) in its (n, m) blocks."""
    j0, j1, k0, k1, fs, fc = q[0], q[1], q[2], q[3], q[4], q[5]
    D = np.zeros((n + 1, m + 1), np.int64)
    for e in range(ds.shape[0]):
        if ds[e] >= j0 and ds[e] < j1 and dc[e] >= k0 and dc[e] < k1:
            D[(ds[e] - j0) // fs + 1, (dc[e] - k0) // fc + 1] += np.int64(cnt[e])
    for r in range(1, n + 1):
        acc = 0
        for c in range(1, m + 1):
            acc += D[r, c]
            D[r, c] = D[r - 1, c] + acc
    return D


def _background_sums_py(lo, hi, nps, powers, q, n, m):  # pragma: no cover - numba
    """The running sums of the window's background over its first ``n`` rows and ``m``
    columns (``_background_rows_py``, then ``_running_sums_py``, of the rows with
    background): (t + 1, m + 1) with a leading row and column of zeros, and (n + 1,)
    the row of them after each of the window's first 0..n rows.  A block inside a row's
    accepted codes takes the shots times its difference of powers, made once."""
    j0, j1, k0, k1, fs, fc = q[0], q[1], q[2], q[3], q[4], q[5]
    c_lo, cell, coarse = q[12], q[13], q[11] != 0
    width, top = cell * fc, c_lo + cell * k1 - 1  # a block's codes, the window's last code
    diff = np.empty(m)  # a whole block's difference of powers
    for k in range(m):
        e_lo = c_lo + cell * (k0 + fc * k)
        diff[k] = powers[e_lo - c_lo] - powers[min(e_lo + width - 1, top) - c_lo + 1]
    R = np.zeros(n + 1, np.int64)
    C = np.empty((n + 1, m + 1))
    C[0, :] = 0.0
    col = np.zeros(m)
    t = 0
    for r in range(n):
        if coarse:
            a_lo, a_hi, shots = np.iinfo(np.int64).max, -1, 0.0
            for j in range(r * fs, min(j1, (r + 1) * fs)):
                if nps[j] > 0 and lo[j] <= hi[j]:
                    a_lo, a_hi, shots = min(a_lo, lo[j]), max(a_hi, hi[j]), shots + nps[j]
        else:
            a_lo, a_hi, shots = lo[j0 + r], hi[j0 + r], nps[j0 + r]
        if shots > 0 and a_lo <= a_hi:
            # the blocks the accepted codes meet: k_a .. k_b (whole ones strictly inside)
            k_a = max(0, ((a_lo - c_lo) // cell - k0) // fc)
            k_b = min(m - 1, ((a_hi - c_lo) // cell - k0) // fc)
            for k in range(k_a, k_b + 1):
                e_lo = c_lo + cell * (k0 + fc * k)
                e_hi = min(e_lo + width - 1, top)
                if k > k_a and k < k_b:
                    col[k] = col[k] + shots * diff[k]
                else:
                    a, b = max(e_lo, a_lo), min(e_hi, a_hi)
                    if b >= a:
                        col[k] = col[k] + shots * (powers[a - c_lo] - powers[b - c_lo + 1])
            t += 1
            acc = 0.0
            C[t, 0] = 0.0
            for k in range(m):
                acc = acc + col[k]
                C[t, k + 1] = acc
        R[r + 1] = t
    return C, R


def best_rows_py(ds, dc, cnt, lo, hi, nps, powers, p, min_counts):  # pragma: no cover
    """The boxes :func:`~mems_stereo.pipeline.matched_best_kernel.best_kernel_py`'s
    search lets the choice take (``p`` as there), by :func:`window_py`: (K, 4) float64
    rows of step, cell (of the grid), count and background, in search order, of the
    boxes that may hold the smallest tail (:func:`_rows_py`)."""
    q, none = np.empty(16, np.int64), np.zeros(0, np.int64)
    if p[0] * p[1] <= p[4]:  # the whole grid, every valid box
        _query(0, p, none, none, 1, q)
        ij, vals, m = _window(ds, dc, cnt, lo, hi, nps, powers, q, min_counts)
        return _rows(ij, vals, 0, 0, False)
    _query(-1, p, none, none, 1, q)  # the coarse window: its best blocks
    ij, vals, m = _window(ds, dc, cnt, lo, hi, nps, powers, q, min_counts)
    ranked, dev = ij[0] * m + ij[1], np.empty(ij.shape[1])
    for i in range(dev.size):
        dev[i] = _deviance(vals[0, i], vals[1, i])
    top = _largest(dev, min(COARSE_TOP, dev.size))
    rows = np.empty((0, 4))
    for t in range(top.size):
        j0, k0 = _query(t, p, ranked, top, m, q)
        ij, vals, m2 = _window(ds, dc, cnt, lo, hi, nps, powers, q, min_counts)
        more = _rows(ij, vals, j0, k0, True)
        grown = np.empty((rows.shape[0] + more.shape[0], 4))
        grown[:rows.shape[0]], grown[rows.shape[0]:] = rows, more
        rows = grown
    return rows


def _deviance_py(n, b):  # pragma: no cover - numba
    """The Poisson deviance of count ``n``, background ``b`` floored at 1e-12
    (``_add_rows_py``'s and ``_ranks_py``'s expression)."""
    b = max(b, 1e-12)
    return n * math.log(n / b) - (n - b)


def _rows_py(ij, vals, j0, k0, prefilter):  # pragma: no cover - numba
    """The valid boxes of a window (:func:`window_py`) that may hold the smallest
    Poisson tail, as rows (step, cell, count, background) of the grid (offset ``j0``,
    ``k0``), in order; ``prefilter``: of those within DEVIANCE_MARGIN of the window's
    largest deviance (``_add_rows_py``).

    Among boxes of one count the tail and the deviance are monotone in the background
    (the tail rises by at least half the background's relative rise, the deviance
    falls by (N − B) times it): a box whose background exceeds the smallest of its
    count by more than :data:`NEAR_TIE` (relative) has a larger tail than that box,
    by far more than SciPy's rounding, and a smaller deviance by far more than the
    logarithm's (where N − B > :data:`DEGENERATE` · N; else every box of the count is
    kept).  Such a box can neither be chosen nor tie, nor hold the largest deviance,
    and is left out: the choice, and the floor of the prefilter, are the same."""
    K = ij.shape[1]
    n_max = 0
    for i in range(K):
        n_max = max(n_max, int(vals[0, i]))
    b_min = np.full(n_max + 1, np.inf)
    for i in range(K):
        n = int(vals[0, i])
        b_min[n] = min(b_min[n], max(vals[1, i], 1e-12))
    keep = np.zeros(K, np.bool_)
    dev = np.full(K, -np.inf)
    for i in range(K):
        n = int(vals[0, i])
        b = max(vals[1, i], 1e-12)
        keep[i] = b <= b_min[n] * (1.0 + NEAR_TIE) or n - b_min[n] < DEGENERATE * n
        if keep[i] and prefilter:
            dev[i] = _deviance(vals[0, i], vals[1, i])
    if prefilter and K:
        floor = dev.max() - DEVIANCE_MARGIN
        for i in range(K):
            keep[i] = keep[i] and dev[i] >= floor
    rows, k = np.empty((keep.sum(), 4)), 0
    for i in range(K):
        if keep[i]:
            rows[k, 0], rows[k, 1] = j0 + ij[0, i], k0 + ij[1, i]
            rows[k, 2], rows[k, 3] = vals[0, i], vals[1, i]
            k += 1
    return rows


def _search_py(data, cand_i, cand_f, par_i, par_f, i, a, b, whole, res):  # pragma: no cover
    """:meth:`~mems_stereo.pipeline.matched._CandidateSearch.search` of candidate ``i``
    over steps ``a..b`` (``whole``: its whole scan): ``res`` = (p, step, code, count,
    background, level, code positions per window); returns its status."""
    ent, cnt, lo_t, hi_t, nps = data
    n, pix = b - a + 1, cand_i[i, PIXEL]
    # steps accepting a code, lowest, highest, area, widest
    lo, hi, acc = _intervals(nps, lo_t, hi_t, pix, a, b)
    e_min, e_max, ne = np.iinfo(np.int64).max, np.iinfo(np.int64).min, 0
    for t in range(cand_i[i, START], cand_i[i, END]):
        if ent[0, t] >= a and ent[0, t] <= b:
            e_min, e_max, ne = min(e_min, ent[1, t]), max(e_max, ent[1, t]), ne + 1
    if acc[0] == 0 or ne == 0:
        return NO_BOX
    m, cell = par_i[0], par_i[1]
    c_lo, c_hi = max(acc[1], e_min - m), min(acc[2], e_max + m)
    nc = (c_hi - c_lo) // cell + 1
    if nc < 1:
        return FALLBACK
    powers = np.empty(cell * nc + 1)
    for t in range(powers.size):
        powers[t] = math.exp((c_lo - 1 + t) * cand_f[i, 0])
    ds, dc, w, k = np.empty(ne, np.int64), np.empty(ne, np.int64), np.empty(ne), 0
    for t in range(cand_i[i, START], cand_i[i, END]):
        if ent[0, t] >= a and ent[0, t] <= b:
            ds[k], dc[k], w[k] = ent[0, t] - a, (ent[1, t] - c_lo) // cell, cnt[t]
            k += 1
    p = np.array([n, nc, par_i[3], 2 * par_i[2] + 1, par_i[5] if whole else par_i[4], c_lo,
                  cell], np.int64)
    rows = _best_rows(ds, dc, w, lo, hi, nps[a:b + 1], powers, p, par_f[0])
    st = _choose(rows, res)
    if st != BOX:
        return st
    n_w, box_codes = cand_f[i, 1], (2 * par_i[2] + 1) * cell
    if whole:
        ncp = max(1.0, float(acc[3]) / (par_i[3] * box_codes) / max(1.0, n_w))
    else:
        ncp = max(1.0, float(acc[4]) / box_codes)
    res[1], res[2] = a + res[1], c_lo + res[2] * cell + cell // 2
    res[5], res[6] = par_f[1] / (max(1.0, n_w) * ncp), ncp
    return BOX


def frame_kernel_py(ent, cnt, cand_i, cand_f, lo_t, hi_t, nps, par_i, par_f):  # pragma: no cover
    """Every candidate's search of :func:`~mems_stereo.pipeline.matched.score_candidates`.

    ``ent`` (2, E) int64: the counted entries' steps and codes, candidate by candidate
    (``cand_i[:, START:END]``); ``cnt`` (E,) float64 their counts; ``cand_i`` (C, 7)
    int64 (START … STEP_HI); ``cand_f`` (C, 2) float64: ln(1 − h) and the footprint
    windows of the scan; ``lo_t``, ``hi_t`` (S, P) the interval table; ``nps`` (S,)
    valid shots per step; ``par_i`` = (m, cell, half box in cells, footprint, full
    cells, full cells of a whole scan) int64; ``par_f`` = (min_counts, the stage's
    false alarm).  Returns (C, 8) float64: STATUS … CODE_POS."""
    out = np.zeros((cand_i.shape[0], 8))
    data = (ent, cnt, lo_t, hi_t, nps)
    res, res2 = np.zeros(7), np.zeros(7)
    for i in range(cand_i.shape[0]):
        if cand_i[i, END] <= cand_i[i, START]:
            continue
        lo_l, hi_l = cand_i[i, LOCAL_LO], cand_i[i, LOCAL_HI]
        st = NO_BOX
        if lo_l >= 0:
            st = _search(data, cand_i, cand_f, par_i, par_f, i, lo_l, hi_l, False, res)
        a, b = cand_i[i, STEP_LO], cand_i[i, STEP_HI]
        if st != FALLBACK and not (st == BOX and res[0] < res[5]) and (lo_l != a or hi_l != b):
            st2 = _search(data, cand_i, cand_f, par_i, par_f, i, a, b, True, res2)
            if st2 == FALLBACK or (st2 == BOX and (st != BOX or res2[0] < res2[5])):
                st = st2
                res[:] = res2
        out[i, STATUS] = st
        if st == BOX:
            out[i, STEP], out[i, CODE], out[i, COUNT] = res[1], res[2], res[3]
            out[i, BACKGROUND], out[i, P], out[i, LEVEL] = res[4], res[0], res[5]
            out[i, CODE_POS] = res[6]
    return out


def _bound_kernel(py_func):
    """The compiled ``py_func`` (:func:`frame_kernel_py` or :func:`grid_box_py`): SciPy's
    pdtrc linked, and the window, the grid's search and the candidate's search each
    compiled (and cached) as its own function first (inlined into one another they
    would take minutes to compile), their small helpers inlined."""
    global _pdtrc, _window, _best_rows, _search
    if not _BOUND:  # before any kernel that calls them compiles or loads
        _pdtrc = scipy_pdtrc()
        _window = compiled_kernel(window_py, {"_count_sums": _count_sums_py,
                                              "_background_sums": _background_sums_py})
        _best_rows = compiled_kernel(best_rows_py, {
            "_rows": _rows_py, "_deviance": _deviance_py, "_query": window_query_py,
            "_largest": WINDOW_HELPERS["_largest_inline"]})
        _search = compiled_kernel(_search_py, {"_choose": choose_py,
                                                "_intervals": step_intervals_py})
        _BOUND.append(True)
    return compiled_kernel(py_func, {"_choose": choose_py})


def frame_search(ent, cnt, cand_i, cand_f, table, nps, par_i, par_f) -> np.ndarray:
    """:func:`frame_kernel_py`, compiled (numba's disk cache), on the interval table
    ``table`` (its ``lo``, ``hi`` (S, P), every row a candidate reads filled)."""
    kernel = _bound_kernel(frame_kernel_py)
    return kernel(np.ascontiguousarray(ent, np.int64), np.ascontiguousarray(cnt, np.float64),
                  np.ascontiguousarray(cand_i, np.int64), np.ascontiguousarray(cand_f, np.float64),
                  table.lo, table.hi, np.ascontiguousarray(nps, np.float64),
                  np.asarray(par_i, np.int64), np.asarray(par_f, np.float64))


def grid_box_py(ds, dc, cnt, lo, hi, nps, powers, p, min_counts):  # pragma: no cover
    """One grid's search and choice (:func:`best_rows_py`, :func:`choose_py`; ``p`` as
    :func:`~mems_stereo.pipeline.matched_best_kernel.best_kernel_py`'s): (6,) float64,
    the status, then p, step, cell, count and background."""
    res = np.zeros(7)
    st = _choose(_best_rows(ds, dc, cnt, lo, hi, nps, powers, p, min_counts), res)
    out = np.zeros(6)
    out[0] = st
    out[1:] = res[:5]
    return out


def search_grid(grid, box_s: int, box_c: int, min_counts: int, full_cells: int):
    """The box :func:`frame_kernel_py` chooses on a
    :class:`~mems_stereo.pipeline.matched_grid.CompiledGrid` ``grid`` (its fields),
    as ``(status, BestBox fields p, j, k, count, background)`` (6,) float64."""
    p = np.array([grid.n_steps, grid.n_cell, box_s, box_c, full_cells, grid.c_lo, grid.cell],
                 np.int64)
    return _bound_kernel(grid_box_py)(grid.ds, grid.dc, np.asarray(grid.cnt, np.float64),
                                      grid.lo, grid.hi, grid.nps, grid.powers, p,
                                      float(min_counts))


#: the kernels the frame kernel calls (bound to their compiled forms by
#: :func:`_bound_kernel`)
_pdtrc = _pdtrc_py
_BOUND: list = []
_choose = choose_py
_search = _search_py
_intervals = step_intervals_py
_window = window_py
_background_sums = _background_sums_py
_count_sums = _count_sums_py
_best_rows = best_rows_py
_deviance = _deviance_py
_rows = _rows_py
_query = window_query_py
_largest = WINDOW_HELPERS["_largest_inline"]
