"""A candidate's whole box search in one compiled call (:class:`BestBoxGrid`).

:meth:`~mems_stereo.pipeline.matched_boxes.BoxGrid.best` searches a large grid coarse to
fine: one window of blocks ranked by the Poisson deviance, then up to
:data:`~mems_stereo.pipeline.matched_boxes.COARSE_TOP` exact windows around the best
blocks, each choosing its box of smallest Poisson tail; a small grid is one exact
window.  :class:`~mems_stereo.pipeline.matched_grid.CompiledGrid` compiles each window;
:func:`best_kernel_py` runs every window of the search in one call (a frame's matched
filter searches a few hundred candidates, and a call per window cost more than its
arithmetic) and returns the boxes the choice may take; the Poisson tails (SciPy's
``pdtrc``) are then evaluated in one call and the box chosen as
:func:`~mems_stereo.pipeline.matched_boxes.pick_box` and ``best`` choose it.

The same numbers: the windows are the same kernel's; the ranking and the refinement's
deviance screen use numba's logarithm where NumPy's is used there (the same function
of the C library on CPUs where NumPy has no vectorised float64 logarithm, as here:
the same bits; elsewhere a box within a unit in the last place of a screen's edge
could differ).  The tails are evaluated at every box the window's screen keeps, not
only at :func:`~mems_stereo.pipeline.matched_boxes._contenders`' subset: that subset
leaves out only boxes whose tail is provably larger than the smallest, so the first
smallest over windows and boxes in search order is the same box with the same value.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import pdtrc

from mems_stereo.pipeline.matched_boxes import (
    COARSE_BOX_UNITS,
    COARSE_TOP,
    DEVIANCE_MARGIN,
    FULL_SCAN_CELLS,
    BestBox,
)
from mems_stereo.pipeline.matched_grid import (
    EVERY,
    NEAR_MAX,
    TOP,
    WINDOW_HELPERS,
    CompiledGrid,
    window_kernel_py,
)
from mems_stereo.util.lazy_numba import compiled_kernel

#: where a search's boxes are laid out in the kernel's rows
WINDOW, STEP, CELL, COUNT, BACKGROUND = range(5)


class BestBoxGrid(CompiledGrid):
    """A :class:`~mems_stereo.pipeline.matched_grid.CompiledGrid` (same fields and
    results) whose :meth:`best` runs the whole search in one kernel call
    (:func:`best_kernel_py`)."""

    def best(self, box_s: int, box_c: int, min_counts: int,
             full_cells: int | None = None) -> BestBox | None:
        """:meth:`~mems_stereo.pipeline.matched_boxes.BoxGrid.best` (the same box, p,
        count and background)."""
        full = FULL_SCAN_CELLS if full_cells is None else full_cells
        p = np.array([self.n_steps, self.n_cell, box_s, box_c, full, self.c_lo, self.cell],
                     np.int64)
        kernel = best_kernel()
        rows, wins = kernel(self.ds, self.dc, np.asarray(self.cnt, np.float64), self.lo,
                            self.hi, self.nps, self.powers, p, float(min_counts))
        return choose_box(rows, wins)


def best_kernel():
    """The compiled :func:`best_kernel_py`, its small helpers inlined and the window
    kernel called as its own compiled (and cached) function: compiling it inlined
    would cost twice the time."""
    global _window
    _window = compiled_kernel(window_kernel_py, WINDOW_HELPERS)
    return compiled_kernel(best_kernel_py, _BEST_HELPERS)


def choose_box(rows, wins) -> BestBox | None:
    """The box ``best`` chooses from :func:`best_kernel_py`'s ``rows`` (K, 5) and
    ``wins`` (W, 4): each window's box of smallest Poisson tail (the first; where no
    tail is below 1 or one is NaN, as :func:`~mems_stereo.pipeline.matched_boxes.pick_box`
    falls back), the first window's unless a later one's tail is smaller; None where
    no window holds a box."""
    if rows.shape[0] == 0:
        return None
    with np.errstate(invalid="ignore"):
        pt = pdtrc(np.maximum(rows[:, COUNT] - 1, 0), np.maximum(rows[:, BACKGROUND], 1e-12))
    if not np.isnan(pt).any() and pt.min() < 1.0:  # the first smallest, in search order
        return _box(rows[int(np.argmin(pt))], pt.min())
    out = None
    for w in range(wins.shape[0]):  # a window whose tails are all 1, or one is NaN
        sel = np.flatnonzero(rows[:, WINDOW] == w)
        if not sel.size:
            continue
        t = pt[sel]
        nan = np.flatnonzero(np.isnan(t))
        if nan.size:
            r = _box(rows[sel[nan[0]]], np.nan)
        elif t.min() < 1.0:
            r = _box(rows[sel[int(np.argmin(t))]], t.min())
        else:  # pick_box's box (0, 0) of the window, p 1
            r = BestBox(1.0, int(wins[w, 0]), int(wins[w, 1]), wins[w, 2], wins[w, 3])
        if out is None or r.p < out.p:
            out = r
    return out


def _box(row, p) -> BestBox:
    return BestBox(float(p), int(row[STEP]), int(row[CELL]), row[COUNT], row[BACKGROUND])


def step_intervals_py(nps, lo_t, hi_t, pix, a, b):  # pragma: no cover - numba
    """The matched filter's accepted codes of pixel ``pix`` at steps a..b
    (:meth:`~mems_stereo.pipeline.matched._CandidateSearch.intervals`): ``lo``, ``hi``
    (b − a + 1,) int64 from the interval table ``lo_t``, ``hi_t`` (S, P) (1, 0 where
    ``nps`` (S,), the valid shots, is 0) and (5,) int64: the steps accepting a code,
    their lowest and highest code, Σ(hi − lo + 1) and the widest interval (all 0
    where no step accepts a code)."""
    n = b - a + 1
    lo, hi = np.empty(n, np.int64), np.empty(n, np.int64)
    out = np.zeros(5, np.int64)
    out[1], out[2] = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    for j in range(n):
        lo[j], hi[j] = 1, 0
        if nps[a + j] > 0:
            lo[j], hi[j] = lo_t[a + j, pix], hi_t[a + j, pix]
        if lo[j] <= hi[j]:
            out[0] += 1
            out[1], out[2] = min(out[1], lo[j]), max(out[2], hi[j])
            out[3] += hi[j] - lo[j] + 1
            out[4] = max(out[4], hi[j] - lo[j] + 1)
    if out[0] == 0:
        out[1], out[2] = 0, 0
    return lo, hi, out


def best_kernel_py(ds, dc, cnt, lo, hi, nps, powers, p, min_counts):  # pragma: no cover
    """The windows of ``BoxGrid.best`` (``p`` = (n_steps, n_cell, box_s, box_c,
    full_cells, c_lo, cell)), each by :func:`~mems_stereo.pipeline.matched_grid.window_kernel_py`:
    the whole grid where it has at most ``full_cells`` cells, else the coarse window
    (blocks of about 1/COARSE_BOX_UNITS of a box) ranked by the deviance and the exact
    window around each of its COARSE_TOP best blocks, its boxes screened to those
    within DEVIANCE_MARGIN of its largest deviance.  Returns ``rows`` (K, 5) float64:
    per box the choice may take its window (0, 1, … in search order), step and cell
    (of the grid), count and background; ``wins`` (W, 4): each window's first step and
    cell and the count and background of its box (0, 0) (W = 0: the coarse window
    holds no box)."""
    coarse = p[0] * p[1] > p[4]
    rows = np.empty((64, 5))
    k = 0
    wins = np.empty((COARSE_TOP if coarse else 1, 4))
    ranked, top = np.zeros(0, np.int64), np.zeros(0, np.int64)
    m = 1
    w, n_win = (-1 if coarse else 0), 1
    q = np.empty(16, np.int64)
    while w < n_win:  # (one call site of the window kernel: compiled once)
        j0, k0 = _query(w, p, ranked, top, m, q)
        sums, flat = _window(ds, dc, cnt, lo, hi, nps, powers, q, min_counts)
        if w < 0:  # the coarse window: its best blocks
            if flat.size == 0:
                return rows[:0], wins[:0]
            ranked, m = flat.copy(), sums.shape[2]
            top = _ranks(sums, ranked)
            n_win = top.size
        else:
            rows, k = _add_rows(rows, k, sums, flat, w, wins, j0, k0, coarse)
        w += 1
    return rows[:k], wins[:n_win]


def window_query_py(w, p, ranked, top, m, q):  # pragma: no cover - compiled by numba
    """The window kernel's parameters ``q`` (16,) of window ``w`` of the search (-1: the
    coarse window; 0 … : the whole grid, or the refinement around the coarse block
    ``ranked[top[w]]`` of a coarse window ``m`` blocks wide), written in place;
    returns the window's first step and cell."""
    n, nc, box_s, box_c = p[0], p[1], p[2], p[3]
    j0, j1, k0, k1, fs, fc, bs, bc = 0, n, 0, nc, 1, 1, box_s, box_c
    mode, coarse, top_n = EVERY, 0, 0
    if n * nc > p[4]:
        fs, fc = max(1, box_s // COARSE_BOX_UNITS), max(1, box_c // COARSE_BOX_UNITS)
        cs, cc = -(-box_s // fs) | 1, -(-box_c // fc) | 1
        if w < 0:
            bs, bc, mode, coarse, top_n = cs, cc, TOP, 1, COARSE_TOP
        else:
            jc, kc = ranked[top[w]] // m, ranked[top[w]] % m
            j0, j1 = max(0, (jc - cs // 2 - 1) * fs), min(n, (jc + cs // 2 + 2) * fs)
            k0, k1 = max(0, (kc - cc // 2 - 1) * fc), min(nc, (kc + cc // 2 + 2) * fc)
            fs, fc, mode = 1, 1, NEAR_MAX
    q[0], q[1], q[2], q[3], q[4], q[5], q[6], q[7] = j0, j1, k0, k1, fs, fc, bs, bc
    q[8], q[9], q[10], q[11] = 1 if k0 == 0 else 0, 1 if k1 == nc else 0, mode, coarse
    q[12], q[13], q[14], q[15] = p[5], p[6], nc, top_n
    return j0, k0


def _ranks_py(sums, ranked):  # pragma: no cover - compiled by numba
    """The indices into ``ranked`` of the coarse window's COARSE_TOP boxes of largest
    deviance, largest first (ties: the first; ``pick_box``'s stable ranking)."""
    dev = np.empty(ranked.size)
    for i in range(ranked.size):
        v, b = sums[0].ravel()[ranked[i]], max(sums[1].ravel()[ranked[i]], 1e-12)
        dev[i] = v * math.log(v / b) - (v - b)
    return _largest(dev, min(COARSE_TOP, ranked.size))


def _add_rows_py(rows, k, sums, flat, w, wins, j0, k0, prefilter):  # pragma: no cover
    """Window ``w``'s boxes ``flat`` (offset ``j0``, ``k0`` in the grid) appended to
    ``rows`` from row ``k`` (grown as needed), and its box (0, 0) to ``wins[w]``;
    ``prefilter``: only those within DEVIANCE_MARGIN of the window's largest deviance
    (``pick_box``'s prefilter).  Returns ``(rows, k + the rows added)``."""
    N, B = sums[0].ravel(), sums[1].ravel()
    m = sums.shape[2]
    wins[w, 0], wins[w, 1], wins[w, 2], wins[w, 3] = j0, k0, N[0], B[0]
    dev = np.empty(flat.size)
    for i in range(flat.size):
        v, b = N[flat[i]], max(B[flat[i]], 1e-12)
        dev[i] = v * math.log(v / b) - (v - b)
    floor = dev.max() - DEVIANCE_MARGIN if (prefilter and flat.size) else -np.inf
    for i in range(flat.size):
        if prefilter and not dev[i] >= floor:
            continue
        if k == rows.shape[0]:
            grown = np.empty((2 * k, 5))
            grown[:k] = rows
            rows = grown
        f = flat[i]
        rows[k, 0], rows[k, 1], rows[k, 2] = w, j0 + f // m, k0 + f % m
        rows[k, 3], rows[k, 4] = N[f], B[f]
        k += 1
    return rows, k


#: the kernels :func:`best_kernel_py` calls (bound to their compiled forms by
#: :func:`best_kernel`)
_window = window_kernel_py
_largest = WINDOW_HELPERS["_largest_inline"]
_add_rows = _add_rows_py
_query = window_query_py
_ranks = _ranks_py
_BEST_HELPERS = {"_add_rows": _add_rows_py, "_largest": WINDOW_HELPERS["_largest_inline"],
                 "_query": window_query_py, "_ranks": _ranks_py}
