"""The matched filter's box search over one window of a candidate's grid in one compiled
kernel: counts, expected background, box sums and the valid boxes at once
(:class:`CompiledGrid`, a :class:`~mems_stereo.pipeline.matched_boxes.BoxGrid` whose
:meth:`~mems_stereo.pipeline.matched_boxes.BoxGrid.search_window` is compiled).

The kernel makes the same numbers as the NumPy stages it replaces, addition for
addition: the counts added in entry order (:meth:`BoxGrid.counts`), the background
``nps · ((1 − h)^(a−1) − (1 − h)^b)`` from one table of powers computed by NumPy
(:meth:`BoxGrid.background`; a block of steps takes the valid shots and the union of
the accepted codes of its steps, :meth:`BoxGrid.coarse_background`: the shots are
whole numbers, so their sum is exact in any order), the box sums of
:func:`~mems_stereo.pipeline.matched_boxes.box_sums_py` and the valid boxes of
:func:`~mems_stereo.pipeline.matched_boxes.valid_boxes`.  Logarithms, tails and the
choice stay NumPy's and SciPy's
(:func:`~mems_stereo.pipeline.matched_boxes.pick_box`); the kernel only leaves out
boxes that cannot be chosen (:func:`screened_boxes_py`: bounds on the deviance and on
the Poisson tail, with a margin far above the difference between numba's logarithm
and NumPy's).  Rows of a window without counts or background (angle steps the frame
did not visit) add nothing to the running sums and are skipped.
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.pipeline.matched_boxes import DEVIANCE_MARGIN, BoxGrid, pick_box
from mems_stereo.util.lazy_numba import compiled_kernel

#: relative margin for the kernel's deviance against NumPy's (both logarithms within a
#: few units in the last place: ~1e-15 relative; this is a million times that)
SCREEN_RELATIVE = 1e-9

#: the largest deviance at which the tails' bound leaves boxes out (exp(−600) ≈ 1e-261:
#: no tail near it underflows)
SCREEN_MAX_DEVIANCE = 600.0

#: the kernel's modes: every valid box, the top ranks only (the coarse search), the
#: boxes within :data:`DEVIANCE_MARGIN` of the largest deviance only (the refinement)
EVERY, TOP, NEAR_MAX = 0, 1, 2


class CompiledGrid(BoxGrid):
    """A :class:`BoxGrid` (same fields and results) searched by one compiled kernel per
    window (:func:`window_kernel_py`); ``lo``, ``hi`` int64 and ``nps`` float64 (whole
    numbers of valid shots), ``ds``, ``dc`` int64.  Used where numba is loaded."""

    def __init__(self, ds, dc, cnt, lo, hi, nps, c_lo, cell, log1mh, n_cell):
        super().__init__(ds, dc, cnt, lo, hi, nps, c_lo, cell, log1mh, n_cell)
        # (1 − h)^k for the codes k a cell and an accepted interval can share, k from
        # c_lo − 1 (NumPy's exp: the numbers of BoxGrid.background's table)
        self.powers = np.exp(np.arange(c_lo - 1, c_lo + cell * n_cell) * log1mh)

    def search_window(self, win, blocks, box, min_counts: int, cut=(True, True),
                      top: int = 0, prefilter: bool = False, coarse: bool = False):
        """:meth:`BoxGrid.search_window` in one kernel call (the same box, the same
        numbers)."""
        mode = TOP if top else (NEAR_MAX if prefilter else EVERY)
        q = np.array([*win, *blocks, *box, cut[0], cut[1], mode, coarse, self.c_lo,
                      self.cell, self.n_cell, top], np.int64)
        kernel = compiled_kernel(window_kernel_py, _HELPERS)
        sums, flat = kernel(self.ds, self.dc, np.asarray(self.cnt, np.float64), self.lo,
                            self.hi, self.nps, self.powers, q, float(min_counts))
        return pick_box(sums[0], sums[1], flat, top, prefilter)


def window_kernel_py(ds, dc, cnt, lo, hi, nps, powers, q, min_counts):  # pragma: no cover
    """:meth:`CompiledGrid.search_window`'s kernel: ``q`` = (j0, j1, k0, k1, fs, fc,
    box_s, box_c, cut_lo, cut_hi, mode, coarse, c_lo, cell, n_cell, top); returns the
    box sums (2, n, m) float64 of counts and background (NaN where no valid box lies
    but at [:, 0, 0]; the background's only where the count is at least
    ``min_counts``) and the flat indices (int64, ascending) of the valid boxes that
    :func:`screened_boxes` keeps."""
    j0, j1, k0, k1, fs, fc = q[0], q[1], q[2], q[3], q[4], q[5]
    n0, n1 = (j1 - j0 + fs - 1) // fs, (k1 - k0 + fc - 1) // fc
    A = np.zeros((2, n0, n1))
    busy = np.zeros(n0, np.bool_)  # rows that may hold a nonzero count or background
    for e in range(ds.shape[0]):  # the counts, in entry order (BoxGrid.counts)
        j, k = ds[e], dc[e]
        if j >= j0 and j < j1 and k >= k0 and k < k1:
            A[0, (j - j0) // fs, (k - k0) // fc] += cnt[e]
            busy[(j - j0) // fs] = True
    _background_rows(A, busy, lo, hi, nps, powers, q)
    sums, flat = _box_scan_inline(A, busy, q[6], q[7], min_counts, q[8] != 0, q[9] != 0)
    return sums, _screened_inline(sums, flat, q[10], q[15])


def _background_rows_py(A, busy, lo, hi, nps, powers, q):  # pragma: no cover - numba
    """``A[1]`` = the expected background of the window's rows × blocks of cells
    (:meth:`BoxGrid.background`; ``coarse``: blocks of ``fs`` steps from step 0, each
    its shots over the union of its steps' accepted codes,
    :meth:`BoxGrid.coarse_background`), ``busy`` set where a row is written.  A row
    without shots or accepted codes stays +0.0 (what ``shots · 0.0`` and
    ``0 · (a difference >= 0)`` give)."""
    j0, j1, k0, k1, fs, fc = q[0], q[1], q[2], q[3], q[4], q[5]
    c_lo, cell, coarse = q[12], q[13], q[11] != 0
    big = np.iinfo(np.int64).max
    for r in range(A.shape[1]):
        if coarse:
            a_lo, a_hi, shots = big, -1, 0.0
            for j in range(r * fs, min(j1, (r + 1) * fs)):
                if nps[j] > 0 and lo[j] <= hi[j]:
                    a_lo, a_hi, shots = min(a_lo, lo[j]), max(a_hi, hi[j]), shots + nps[j]
        else:
            a_lo, a_hi, shots = lo[j0 + r], hi[j0 + r], nps[j0 + r]
        if not (shots > 0 and a_lo <= a_hi):
            continue
        busy[r] = True
        for k in range(A.shape[2]):
            e_lo = c_lo + cell * (k0 + fc * k)
            e_hi = min(e_lo + cell * fc - 1, c_lo + cell * k1 - 1)
            a, b = max(e_lo, a_lo), min(e_hi, a_hi)
            if b >= a:
                A[1, r, k] = shots * (powers[a - c_lo] - powers[b - c_lo + 1])
            else:
                A[1, r, k] = shots * 0.0


def _running_sums_py(A, busy):  # pragma: no cover - numba
    """The running sums of :func:`~mems_stereo.pipeline.matched_boxes.box_sums_py`
    (along the steps, then the cells: the same additions) of the ``busy`` rows of
    ``A`` (2, n, m) only: ``(c, row)``, c (2, rows + 1, m + 1) with a leading row and
    column of zeros, ``row[i]`` (n + 1,) the row of c that holds the running sums after
    A's row i − 1 (a row of +0.0 adds nothing: its sums are the row's before it)."""
    n, m = A.shape[1], A.shape[2]
    row = np.zeros(n + 1, np.int64)
    t = 0
    for i in range(n):
        t += 1 if busy[i] else 0
        row[i + 1] = t
    c = np.zeros((2, t + 1, m + 1))
    col = np.zeros(m)
    for p in range(2):
        col[:] = 0.0
        t = 0
        for i in range(n):
            if busy[i]:
                t += 1
                acc = 0.0
                for j in range(m):
                    col[j] = col[j] + A[p, i, j]
                    acc = acc + col[j]
                    c[p, t, j + 1] = acc
    return c, row


def _box_at_py(c, row, ri, ci, p, i, j, h, w):  # pragma: no cover - numba
    """Box sum ``p`` (0 counts, 1 background) centred at (i, j): the difference of
    the running sums at its corners (:func:`~mems_stereo.pipeline.matched_boxes.box_sums_py`'s
    expression)."""
    a, b = row[ri[i]], row[ri[i + h]]
    x, y = ci[j], ci[j + w]
    return c[p, b, y] - c[p, a, y] - c[p, b, x] + c[p, a, x]


def _valid_boxes_py(A, busy, h, w, min_counts, cut_lo, cut_hi):  # pragma: no cover
    """:func:`~mems_stereo.pipeline.matched_boxes.valid_boxes` of ``A`` = (D, B)
    (2, n, m), loop by loop: the box sums where a box is whole in the first axis and
    within the columns the cut allows (the background's only where the count reaches
    ``min_counts``; both at (0, 0); NaN elsewhere) and the flat indices of the boxes
    there with D ≥ ``min_counts`` and D > B."""
    n, m = A.shape[1], A.shape[2]
    c, row = _running_sums_inline(A, busy)
    i0, j0 = h // 2 + 1, w // 2 + 1  # where A starts in the padded array
    ri = np.empty(n + h, np.int64)
    for i in range(n + h):
        ri[i] = 0 if i < i0 else min(i - i0, n - 1) + 1
    ci = np.empty(m + w, np.int64)
    for j in range(m + w):
        ci[j] = 0 if j < j0 else min(j - j0, m - 1) + 1
    out = np.full((2, n, m), np.nan)
    for p in range(2):
        out[p, 0, 0] = _box_at_inline(c, row, ri, ci, p, 0, 0, h, w)
    half, hc = h // 2, w // 2
    flat = np.empty(n * m, np.int64)
    k = 0
    if n > 2 * half:
        c0 = 0 if cut_lo else hc
        c1 = m if cut_hi else max(0, m - hc)
        for i in range(half, n - half):
            if row[ri[i]] == row[ri[i + h]]:  # no busy row in the box: every sum is
                for j in range(c0, c1):  # x − x − y + y = +0.0 (a step not visited)
                    out[0, i, j] = 0.0
                    if 0.0 >= min_counts:
                        out[1, i, j] = 0.0
                continue
            for j in range(c0, c1):
                N = _box_at_inline(c, row, ri, ci, 0, i, j, h, w)
                out[0, i, j] = N
                if N >= min_counts:
                    B = _box_at_inline(c, row, ri, ci, 1, i, j, h, w)
                    out[1, i, j] = B
                    if N > B:
                        flat[k] = i * m + j
                        k += 1
    return out, flat[:k]


def screened_boxes_py(sums, flat, mode, top):  # pragma: no cover - numba
    """The valid boxes ``flat`` that :func:`~mems_stereo.pipeline.matched_boxes.pick_box`
    may choose: those whose deviance may rank among the ``top`` (mode TOP); else those
    whose Poisson tail may be the smallest, within :data:`DEVIANCE_MARGIN` of the
    largest deviance where NEAR_MAX.  The box of largest deviance D has a tail at most
    exp(−D) (Chernoff), and a box's tail is at least P(X = N) >= exp(−dev − ln(2πN)/2 −
    1/(12N)) (Stirling): a box whose bound lies above exp(−D) cannot hold the smallest
    tail nor tie with it, and is left out (only where exp(−D) is far from underflow:
    D < :data:`SCREEN_MAX_DEVIANCE`).  The deviances here use numba's logarithm: a box
    is left out only when it misses by more than a margin far above the largest
    possible difference from NumPy's, so NumPy's deviances and SciPy's tails choose
    among the rest as among all."""
    if flat.size <= max(top, 1):
        return flat
    N, B = sums[0].ravel(), sums[1].ravel()
    # the deviance is at most (N − B)²/B (ln x <= x − 1) and at least 0: boxes whose
    # bound misses the mark against the deviances of the boxes of largest bound are
    # left out without a logarithm
    u = np.empty(flat.size)
    n_max, nb = 1.0, 0.0
    for i in range(flat.size):
        n, b = N[flat[i]], max(B[flat[i]], 1e-12)
        u[i] = (n - b) * (n - b) / b
        n_max, nb = max(n_max, n), max(nb, n + b)
    slack = SCREEN_RELATIVE * (u.max() + 2.0 * nb) + 1e-9  # above |numba's − NumPy's|
    dev = np.full(flat.size, -np.inf)
    lower = np.inf if mode == TOP else -np.inf
    for i in _largest_inline(u, max(top, 1)):
        n, b = N[flat[i]], max(B[flat[i]], 1e-12)
        dev[i] = n * math.log(n / b) - (n - b)
        lower = min(lower, dev[i]) if mode == TOP else max(lower, dev[i])
    gap = 4.0 * slack  # TOP: the top-th largest deviance is at least ``lower``
    if mode == NEAR_MAX:
        gap += DEVIANCE_MARGIN
    elif mode == EVERY:
        gap += 0.5 * math.log(2.0 * math.pi * n_max) + 1.0 / 12.0 + 1e-6 + 2.0 * slack
    for i in range(flat.size):
        if dev[i] == -np.inf and u[i] >= lower - gap:
            n, b = N[flat[i]], max(B[flat[i]], 1e-12)
            dev[i] = n * math.log(n / b) - (n - b)
    if mode == TOP:  # the top-th largest deviance
        return flat[dev >= dev[_largest_inline(dev, top)[top - 1]] - 2.0 * slack]
    r = np.argmax(dev)
    d_max = dev[r]
    # the smallest tail is at most the tail of box r: exp(−D) and P(X = N)·(N + 1)/(N + 1 − B)
    n, b = N[flat[r]], max(B[flat[r]], 1e-12)
    log_pmf = n * math.log(b) - b - math.lgamma(n + 1.0)
    bound = min(-d_max, log_pmf + math.log((n + 1.0) / (n + 1.0 - b)))
    bound += 1e-6 + 4.0 * slack + SCREEN_RELATIVE * (abs(log_pmf) + 2.0 * b + math.lgamma(n + 1.0))
    if mode == EVERY and bound <= -SCREEN_MAX_DEVIANCE:
        return flat
    keep = dev >= (d_max - DEVIANCE_MARGIN - 2.0 * slack if mode == NEAR_MAX else -np.inf)
    if bound > -SCREEN_MAX_DEVIANCE:
        for i in range(flat.size):
            n = N[flat[i]]
            if n < 1.0:  # (a fractional count: no bound)
                return flat[keep] if mode == NEAR_MAX else flat
            point = -dev[i] - 0.5 * math.log(2.0 * math.pi * n) - 1.0 / (12.0 * n)
            keep[i] = keep[i] and point <= bound
    return flat[keep]


def _largest_py(values, t):  # pragma: no cover - numba
    """The indices of the ``t`` largest of ``values`` (t,) int64, largest first (ties:
    the first), by one pass (t is a few)."""
    idx = np.full(t, -1, np.int64)
    top = np.full(t, -np.inf)
    for i in range(values.size):
        v = values[i]
        if idx[t - 1] >= 0 and v <= top[t - 1]:
            continue
        r = t - 1
        while r > 0 and (idx[r - 1] < 0 or v > top[r - 1]):
            top[r], idx[r] = top[r - 1], idx[r - 1]
            r -= 1
        top[r], idx[r] = v, i
    return idx


def screened_boxes(sums, flat, mode: int, top: int = 0) -> np.ndarray:
    """:func:`screened_boxes_py` (compiled where numba is loaded): the valid boxes
    ``flat`` (int64, ascending) of the box sums ``sums`` (2, n, m) that the choice
    may take, in order."""
    kernel = compiled_kernel(screened_boxes_py, {"_largest_inline": _largest_py})
    return kernel(sums, np.asarray(flat, np.int64), mode, top)


#: the kernels :func:`window_kernel_py` calls (bound to their inlined compiled forms)
_background_rows = _background_rows_py
_screened_inline = screened_boxes_py
_box_scan_inline = _valid_boxes_py
_running_sums_inline = _running_sums_py
_box_at_inline = _box_at_py
_largest_inline = _largest_py
_HELPERS = {"_background_rows": _background_rows_py, "_screened_inline": screened_boxes_py,
            "_box_scan_inline": _valid_boxes_py, "_running_sums_inline": _running_sums_py,
            "_box_at_inline": _box_at_py, "_largest_inline": _largest_py}
#: the same, for kernels that call :func:`window_kernel_py` (compile it with these first)
WINDOW_HELPERS = _HELPERS
