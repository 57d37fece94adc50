"""The matched filter's box search: one candidate's counts and expected background over
its scan-angle steps × code cells, and the (footprint × code) box of smallest Poisson
p-value over them (:class:`BoxGrid`), coarse to fine where the grid is large.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np
from scipy.special import pdtrc

from mems_stereo.util.lazy_numba import compiled_if_loaded, compiled_kernel

#: the most (step × cell) positions a candidate's grid is searched at in full; beyond
#: (a whole scan's band of steps: candidates search it all, see
#: :data:`~mems_stereo.pipeline.peaks.CANDIDATE_WHOLE_SCAN`), coarse to fine
FULL_SCAN_CELLS = 400_000
#: the same for a whole scan's grid (thousands of steps × a narrow interval, where the
#: exhaustive search costs about ten times the coarse one)
WHOLE_SCAN_FULL_CELLS = 50_000
#: coarse blocks per box side in the coarse search (a box quantised to within 1/4)
COARSE_BOX_UNITS = 4
#: coarse boxes refined exactly
COARSE_TOP = 4
#: in the refinement the Poisson tail is evaluated only at boxes whose deviance
#: N ln(N/B) − (N − B) is within this of the largest
DEVIANCE_MARGIN = 5.0
#: boxes below which the Poisson tail is evaluated at every valid box (no pruning)
PRUNE_MIN_BOXES = 64
#: a reference tail below this (near underflow) evaluates every valid box
PRUNE_MIN_TAIL = 1e-280


@dataclass(frozen=True, slots=True)
class BestBox:
    """The box of smallest Poisson p-value over a grid of counts.

    p : float, its Poisson p-value; j, k : int, its centre's step and cell index
    (0-based within the grid searched); count : float, its count; background :
    float, its expected background.
    """

    p: float
    j: int
    k: int
    count: float
    background: float


class BoxGrid:
    """One candidate's counts and expected background over its counted steps × code
    cells, and the smallest Poisson p-value of the (footprint × code) box over them.

    ``ds``, ``dc``, ``cnt`` : (E,) each entry's step and cell index (0-based within
    the candidate's grid) and count; ``lo``, ``hi`` : (n_steps,) the accepted codes of
    each step; ``nps`` : (n_steps,) its valid shots; cell ``k`` holds codes
    ``c_lo + cell·k …`` ; ``log1mh`` : ln(1 − h), h the chance of a background first
    photon per code; ``n_cell`` : the grid's cells.  The background of cell k at step
    j is the valid shots times P(first photon in the cell's codes ∩ [lo_j, hi_j]),
    F(c) = 1 − (1 − h)^c the chance it came by code c (the free-running expectation: conservative).
    """

    def __init__(self, ds, dc, cnt, lo, hi, nps, c_lo, cell, log1mh, n_cell):
        self.ds, self.dc, self.cnt = ds, dc, cnt
        self.lo, self.hi, self.nps = lo, hi, nps
        self.c_lo, self.cell, self.log1mh = c_lo, cell, log1mh
        self.n_steps, self.n_cell = int(np.shape(lo)[0]), n_cell

    def counts(self, j0, j1, k0, k1, fs=1, fc=1):
        """(ceil((j1−j0)/fs), ceil((k1−k0)/fc)) counts of steps j0..j1−1 × cells
        k0..k1−1, summed in blocks of fs steps × fc cells."""
        shape = (-(-(j1 - j0) // fs), -(-(k1 - k0) // fc))
        kernel = compiled_if_loaded(_counts_py)
        if kernel is not None and self.ds.dtype == self.dc.dtype == np.int64:
            return kernel(self.ds, self.dc, np.asarray(self.cnt, np.float64), j0, j1, k0, k1,
                          fs, fc, shape[0], shape[1])
        m = (self.ds >= j0) & (self.ds < j1) & (self.dc >= k0) & (self.dc < k1)
        # the entries added in their order from 0 (np.add.at's additions: the same numbers)
        flat = ((self.ds[m] - j0) // fs) * shape[1] + (self.dc[m] - k0) // fc
        return np.bincount(flat, weights=self.cnt[m],
                           minlength=shape[0] * shape[1]).reshape(shape)

    def background(self, j0, j1, k0, k1, fc=1):
        """The expected background of steps j0..j1−1 × cells k0..k1−1, the cells summed
        in blocks of fc (see :meth:`counts`; :meth:`coarse_background` blocks steps)."""
        e_lo = self.c_lo + self.cell * (k0 + fc * np.arange(-(-(k1 - k0) // fc)))
        e_hi = np.minimum(e_lo + self.cell * fc - 1, self.c_lo + self.cell * k1 - 1)
        lo, hi, nps = self.lo[j0:j1], self.hi[j0:j1], self.nps[j0:j1]
        kernel = compiled_if_loaded(_background_py)
        if kernel is not None and lo.size and e_lo.size:
            # where a cell meets a step's interval, a - 1 and b lie in [k0, k1]
            k0 = max(int(e_lo.min()), int(lo.min())) - 1
            k1 = max(k0, min(int(e_hi.max()), int(hi.max())))
            table = np.exp(np.arange(k0, k1 + 1) * self.log1mh)
            return kernel(np.asarray(lo, np.int64), np.asarray(hi, np.int64),
                          np.asarray(nps, np.float64), e_lo.astype(np.int64),
                          e_hi.astype(np.int64), table, k0)
        a_c = np.maximum(e_lo[None, :], lo[:, None])
        b_c = np.minimum(e_hi[None, :], hi[:, None])
        pr = np.where(b_c >= a_c, _powers(a_c - 1, self.log1mh)
                      - _powers(b_c, self.log1mh), 0.0)
        return nps[:, None] * pr

    def coarse_background(self, fs: int, fc: int):
        """The background of blocks of ``fs`` steps × ``fc`` cells over the whole grid,
        each block of steps taken as its valid shots over the union of its accepted
        codes (an over-estimate at the intervals' ends only: the coarse search ranks
        boxes, the exact background is the refinement's)."""
        n = self.n_steps
        starts = np.arange(0, n, fs)
        shot = (self.nps > 0) & (self.lo <= self.hi)
        big = np.iinfo(np.int64).max
        lo = np.minimum.reduceat(np.where(shot, self.lo, big), starts)
        hi = np.maximum.reduceat(np.where(shot, self.hi, -1), starts)
        nps = np.add.reduceat(np.where(shot, self.nps, 0.0), starts)
        g = BoxGrid(None, None, None, lo, hi, nps, self.c_lo, self.cell, self.log1mh,
                    self.n_cell)
        return g.background(0, starts.size, 0, self.n_cell, fc)

    def search_window(self, win, blocks, box, min_counts: int, cut=(True, True),
                      top: int = 0, prefilter: bool = False, coarse: bool = False):
        """:func:`smallest_p` over the steps ``j0..j1−1`` × cells ``k0..k1−1`` of
        ``win`` = (j0, j1, k0, k1), summed in ``blocks`` = (fs, fc) of steps × cells
        (``coarse``: the whole grid, background by :meth:`coarse_background`), for the
        ``box`` = (steps, cells) (``cut``, ``top``, ``prefilter``: as there)."""
        j0, j1, k0, k1 = win
        D = self.counts(j0, j1, k0, k1, *blocks)
        B = (self.coarse_background(*blocks) if coarse
             else self.background(j0, j1, k0, k1, blocks[1]))
        return smallest_p(D, B, box[0], box[1], min_counts, top, cut, prefilter)

    def best(self, box_s: int, box_c: int, min_counts: int,
             full_cells: int | None = None) -> BestBox | None:
        """The :class:`BestBox` of the box (``box_s`` steps × ``box_c``
        cells, whole in steps) with the smallest Poisson p-value, or None.

        Every box position where the grid holds at most ``full_cells`` (default
        :data:`FULL_SCAN_CELLS`) cells; a larger one (a scan's whole band of steps)
        is searched coarse to fine: boxes of blocks of about
        1/:data:`COARSE_BOX_UNITS` of a box, then the
        exact boxes around the :data:`COARSE_TOP` best of them (a subset of the
        positions: the false-alarm level, set for all of them, holds)."""
        n, nc = self.n_steps, self.n_cell
        if n * nc <= (FULL_SCAN_CELLS if full_cells is None else full_cells):
            return self.search_window((0, n, 0, nc), (1, 1), (box_s, box_c), min_counts)
        fs = max(1, box_s // COARSE_BOX_UNITS)
        fc = max(1, box_c // COARSE_BOX_UNITS)
        bs, bc = -(-box_s // fs) | 1, -(-box_c // fc) | 1
        coarse = self.search_window((0, n, 0, nc), (fs, fc), (bs, bc), min_counts,
                                    top=COARSE_TOP, coarse=True)
        if coarse is None:
            return None
        out = None
        for jc, kc in coarse:
            j0 = max(0, (jc - bs // 2 - 1) * fs)
            j1 = min(n, (jc + bs // 2 + 2) * fs)
            k0 = max(0, (kc - bc // 2 - 1) * fc)
            k1 = min(nc, (kc + bc // 2 + 2) * fc)
            # boxes whole in the window's cells too, except at the grid's own edges
            # (the whole search's boxes run over them; a box cut at the window's edge
            # would lose background the whole one carries)
            r = self.search_window((j0, j1, k0, k1), (1, 1), (box_s, box_c), min_counts,
                                   cut=(k0 == 0, k1 == nc), prefilter=True)
            if r is not None and (out is None or r.p < out.p):
                out = BestBox(r.p, r.j + j0, r.k + k0, r.count, r.background)
        return out


def smallest_p(D, B, box_s: int, box_c: int, min_counts: int, top: int = 0,
               cut=(True, True), prefilter: bool = False):
    """Over the boxes of ``box_s`` × ``box_c`` (whole in the first axis) of counts ``D``
    against background ``B``: the :class:`BestBox` of the smallest Poisson p-value,
    or with ``top`` the (j, k) of the ``top`` smallest; None if no
    box holds ``min_counts`` above its background.  ``cut`` : whether boxes may run
    over the first / last column (else they are whole there too); ``prefilter`` : the
    tail only at boxes whose Poisson deviance is within :data:`DEVIANCE_MARGIN` of the
    largest (the smallest p lies among them: ln p ≈ −deviance up to slowly varying
    terms).  The valid boxes are found by :func:`valid_boxes` and the rest works on
    them alone (the same numbers as over the whole grid)."""
    N_box, B_box, flat = valid_boxes(D, B, box_s, box_c, min_counts, cut)
    return pick_box(N_box, B_box, flat, top, prefilter)


def pick_box(N_box, B_box, flat, top: int = 0, prefilter: bool = False):
    """:func:`smallest_p`'s choice among the valid boxes ``flat`` (flat indices,
    ascending, int64) of the box sums ``N_box``, ``B_box`` (n, m) float64 of counts and
    background.  ``flat`` may leave out boxes that can neither rank among the ``top``
    nor come within :data:`DEVIANCE_MARGIN` of the largest deviance where
    ``prefilter`` (:func:`mems_stereo.pipeline.matched_grid.screened_boxes`): the
    same choice."""
    if flat.size == 0:
        return None
    n_v, b_v = N_box.ravel()[flat], np.maximum(B_box.ravel()[flat], 1e-12)
    if top:  # ranked by the Poisson deviance (a monotone stand-in for the tail's p)
        dev = n_v * np.log(n_v / b_v) - (n_v - b_v)
        order = flat[np.argsort(-dev, kind="stable")[:top]]
        return [divmod(int(k), N_box.shape[1]) for k in order]
    if prefilter:  # the tail only where the deviance is near its largest (ln p ≈ −deviance)
        dev = n_v * np.log(n_v / b_v) - (n_v - b_v)
        keep = dev >= dev.max() - DEVIANCE_MARGIN
        flat, n_v, b_v = flat[keep], n_v[keep], b_v[keep]
    tail = _contenders(n_v, b_v)  # the tail at those boxes only (pdtrc is the cost)
    flat = flat[tail]
    with np.errstate(invalid="ignore"):
        pt = pdtrc(np.maximum(n_v[tail] - 1, 0), b_v[tail])
    if pt.size and not np.isnan(pt).any() and pt.min() < 1.0:
        i = int(np.argmin(pt))  # the first smallest, as over the grid (1 elsewhere)
        k, p_k = int(flat[i]), pt[i]
    else:  # over the whole grid: 1 where not evaluated
        p = np.ones(N_box.size)
        p[flat] = pt
        k = int(np.argmin(p))
        p_k = p[k]
    jj, ci = divmod(k, N_box.shape[1])
    return BestBox(p_k, jj, ci, N_box[jj, ci], B_box[jj, ci])


def valid_boxes(D, B, box_s: int, box_c: int, min_counts: int, cut=(True, True)):
    """``(N_box, B_box, flat)``: the box sums of counts ``D`` and background ``B``
    (n, m) (:func:`box_sums`) and the flat indices (row-major, int64) of the boxes that
    :func:`smallest_p` evaluates: whole in the first axis (and at the columns ``cut``
    forbids), holding at least ``min_counts`` and more than their background.
    Compiled (:func:`_box_scan_py`) where numba is loaded."""
    kernel = None
    if "numba" in sys.modules:  # (as compiled_if_loaded, with the box sums inlined)
        kernel = compiled_kernel(_box_scan_py, {"_box_sums_inline": box_sums_py})
    if kernel is not None:
        sums, flat = kernel(np.ascontiguousarray(np.stack([D, B]), np.float64), int(box_s),
                            int(box_c), float(min_counts), bool(cut[0]), bool(cut[1]))
        return sums[0], sums[1], flat
    N_box, B_box = box_sums(np.stack([D, B]), box_s, box_c)
    half = box_s // 2
    valid = np.zeros(N_box.shape, bool)
    if D.shape[0] > 2 * half:
        valid[half:D.shape[0] - half, :] = True
    hc = box_c // 2
    if not cut[0]:
        valid[:, :hc] = False
    if not cut[1]:
        valid[:, max(0, D.shape[1] - hc):] = False
    valid &= (N_box >= min_counts) & (N_box > B_box)
    return N_box, B_box, np.flatnonzero(valid)


def _contenders(n_v, b_v) -> np.ndarray:
    """Which of the valid boxes (counts ``n_v``, background ``b_v`` floored at 1e-12)
    may hold the smallest Poisson tail: (len,) bool.

    The tail ``P(X >= N | B)`` is at least ``P(X = N | B)``, whose logarithm is, by
    Stirling's bounds on ln N!, at least ``−dev − ln(2πN)/2 − 1/(12N)`` (dev the
    Poisson deviance ``N ln(N/B) − (N − B)``, N >= 1).  A box whose bound lies above
    the tail of the box of largest deviance (by a margin far above the rounding of
    these sums) can neither hold the minimum nor tie with it: the tail is evaluated at
    the rest only, and the minimum is the same box with the same value as over all."""
    every = np.ones(n_v.size, bool)
    if n_v.size < PRUNE_MIN_BOXES:
        return every
    dev = n_v * np.log(n_v / b_v) - (n_v - b_v)
    i = int(np.argmax(dev))
    with np.errstate(invalid="ignore"):
        p_ref = float(pdtrc(max(n_v[i] - 1, 0), b_v[i]))
    if not (p_ref > PRUNE_MIN_TAIL and np.isfinite(dev[i])) or n_v.min() < 1:
        return every  # near underflow, NaN, a fractional count: every valid box
    log_point = -dev - 0.5 * np.log(2 * math.pi * n_v) - 1.0 / (12.0 * n_v)
    margin = 1e-8 * (np.abs(dev) + n_v + b_v) + 1e-9
    return ~(log_point > math.log(p_ref) + margin)


def box_sums(A, h: int, w: int) -> np.ndarray:
    """Centred box sums of (h, w) (odd) over the last two axes of a float64 array
    (k, n, m) or (n, m), zeros beyond its edges: the differences of the running sums
    (along the steps, then the cells) of the array padded with zeros.  Compiled
    (:func:`box_sums_py`, the same additions in the same order: the same numbers)
    where numba is loaded."""
    A = np.asarray(A, np.float64)
    kernel = compiled_if_loaded(box_sums_py)
    if kernel is not None:
        return kernel(np.ascontiguousarray(A.reshape((-1,) + A.shape[-2:])),
                      int(h), int(w)).reshape(A.shape)
    n, m = A.shape[-2:]
    a = np.zeros(A.shape[:-2] + (n + h, m + w))  # A padded with zeros
    a[..., h // 2 + 1:h // 2 + 1 + n, w // 2 + 1:w // 2 + 1 + m] = A
    c = np.cumsum(np.cumsum(a, axis=-2), axis=-1)
    return c[..., h:, w:] - c[..., :-h, w:] - c[..., h:, :-w] + c[..., :-h, :-w]


def box_sums_py(A, h, w):  # pragma: no cover - compiled by numba
    """:func:`box_sums` of a (k, n, m) float64 array, loop by loop (the numba kernel): the
    running sums of A padded with zeros, along the steps (``col``, one row at a time) and
    then along the cells (``c``), each the same addition as in two whole passes.  Only
    A's own rows and cells are summed: the running sums are +0.0 before them (zeros
    added to +0.0; a running sum from +0.0 is never −0.0, so the zeros added after
    them change no bit) and repeat their last value after them; ``c`` holds them
    with a leading row and column of zeros, read through the clamped indices ``ri``,
    ``ci`` of the padded array's rows and cells."""
    k, n, m = A.shape
    i0, j0 = h // 2 + 1, w // 2 + 1  # where A starts in the padded array
    c = np.zeros((n + 1, m + 1))
    col = np.empty(m)
    out = np.empty((k, n, m))
    ri = np.empty(n + h, np.int64)
    for i in range(n + h):
        ri[i] = 0 if i < i0 else min(i - i0, n - 1) + 1
    ci = np.empty(m + w, np.int64)
    for j in range(m + w):
        ci[j] = 0 if j < j0 else min(j - j0, m - 1) + 1
    for q in range(k):
        for j in range(m):
            col[j] = 0.0
        for i in range(n):
            acc = 0.0
            for j in range(m):
                col[j] = col[j] + A[q, i, j]
                acc = acc + col[j]
                c[i + 1, j + 1] = acc
        for i in range(n):
            a, b = ri[i], ri[i + h]
            for j in range(m):
                x, y = ci[j], ci[j + w]
                out[q, i, j] = c[b, y] - c[a, y] - c[b, x] + c[a, x]
    return out


def _box_scan_py(A, h, w, min_counts, cut_lo, cut_hi):  # pragma: no cover - numba
    """:func:`valid_boxes` of ``A`` = (D, B) stacked (2, n, m), loop by loop (the numba
    kernel): the box sums (:func:`box_sums_py`) and the flat indices of the boxes whole
    in the first axis, within the columns the cut allows, with D ≥ ``min_counts`` and
    D > B."""
    out = _box_sums_inline(A, h, w)
    n, m = A.shape[1], A.shape[2]
    half, hc = h // 2, w // 2
    flat = np.empty(n * m, np.int64)
    k = 0
    if n > 2 * half:
        c0 = 0 if cut_lo else hc
        c1 = m if cut_hi else max(0, m - hc)
        for i in range(half, n - half):
            for j in range(c0, c1):
                N = out[0, i, j]
                if N >= min_counts and N > out[1, i, j]:
                    flat[k] = i * m + j
                    k += 1
    return out, flat[:k]


def _counts_py(ds, dc, cnt, j0, j1, k0, k1, fs, fc, n0, n1):  # pragma: no cover - numba
    """:meth:`BoxGrid.counts` loop by loop (the numba kernel): each entry inside steps
    j0..j1−1 × cells k0..k1−1 added to its block, in entry order (``np.bincount``'s
    additions: the same numbers); returns (n0, n1) float64."""
    out = np.zeros((n0, n1))
    for e in range(ds.shape[0]):
        j, k = ds[e], dc[e]
        if j >= j0 and j < j1 and k >= k0 and k < k1:
            a, b = (j - j0) // fs, (k - k0) // fc
            out[a, b] += cnt[e]
    return out


def _background_py(lo, hi, nps, e_lo, e_hi, table, k0):  # pragma: no cover - numba
    """:meth:`BoxGrid.background` loop by loop (the numba kernel): ``lo``, ``hi``,
    ``nps`` (J,) the steps' accepted codes and valid shots, ``e_lo``, ``e_hi`` (K,) the
    cells' codes, ``table[i]`` = exp((k0 + i) · ln(1 − h)); returns (J, K) float64."""
    J, K = lo.shape[0], e_lo.shape[0]
    out = np.empty((J, K))
    for j in range(J):
        for k in range(K):
            a = max(e_lo[k], lo[j])
            b = min(e_hi[k], hi[j])
            if b >= a:
                out[j, k] = nps[j] * (table[a - 1 - k0] - table[b - k0])
            else:
                out[j, k] = nps[j] * 0.0
    return out


#: the kernel :func:`_box_scan_py` calls (bound to its inlined compiled form)
_box_sums_inline = box_sums_py


def _powers(k, log_base) -> np.ndarray:
    """``exp(k · log_base)`` of the integer array ``k`` (float64, the same numbers as
    ``np.exp(k * log_base)``): from a table over ``k``'s range where that is smaller
    than ``k`` (a box grid repeats each code's value over its steps)."""
    k = np.asarray(k)
    if k.size == 0:
        return np.exp(k * log_base)
    k0, k1 = int(k.min()), int(k.max())
    if k1 - k0 + 1 >= k.size:
        return np.exp(k * log_base)
    return np.exp(np.arange(k0, k1 + 1) * log_base)[k - k0]
