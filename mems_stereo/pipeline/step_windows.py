"""The peak detector's window sums over scan-angle steps, on the steps a run visited.

A run (a frame of a live sensor above all) visits U of the interval table's S
angle steps; its signal detections per step and their expected background are
zero at every other step.  The peak detector's moving sums over a footprint of
``width`` steps (:func:`~mems_stereo.physics.background.moving_sum`: differences of
the running sum along the row) are then the same numbers when the running sums
run over the U visited steps alone: the zeros of the others add nothing (the
values are counts and expected counts, ``>= +0``).  A window's sum changes only
where a visited step enters or leaves it, so a row's strongest window
(``numpy.argmax``: the first largest) is found among those positions, and the
row's values need never be laid out over all S steps.

Columns: ``steps`` (U,) int64, the visited steps in increasing order; rows
``counts`` and ``background`` (R, U) float64, their values at those steps.
Kernels are compiled where numba is loaded (:func:`compiled_if_loaded`), with the
same IEEE operations in the same order as their NumPy forms.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from mems_stereo.physics.background import expected_background_at_steps
from mems_stereo.util.lazy_numba import compiled_if_loaded, compiled_kernel


def _loaded() -> bool:
    """Whether numba is imported already (:func:`compiled_if_loaded`'s test, for the
    kernels with a helper)."""
    return "numba" in sys.modules


@dataclass(frozen=True, slots=True)
class WindowEvents:
    """Where the window of ``width`` steps centred at a position changes its set of
    visited steps: ``at`` (E,) int64 positions (0 first, increasing); ``a``, ``b`` (E,)
    int64 the visited steps at or before ``at + width // 2`` and ``at − width // 2 − 1``
    (the running sum's indices, 0 = none) — between two positions the window's sums
    are the same numbers."""

    at: np.ndarray
    a: np.ndarray
    b: np.ndarray


def window_events(steps, n_steps: int, width: int) -> WindowEvents:
    """:class:`WindowEvents` of the visited ``steps`` (U,) of ``n_steps`` (odd ``width``)."""
    steps = np.asarray(steps, np.int64)
    half = int(width) // 2
    mark = np.zeros(int(n_steps) + 1, bool)  # (a last one for the positions beyond)
    mark[0] = True
    mark[np.maximum(steps - half, 0)] = True
    mark[np.minimum(steps + half + 1, int(n_steps))] = True
    at = np.flatnonzero(mark[:-1])
    return WindowEvents(at, np.searchsorted(steps, at + half, side="right"),
                        np.searchsorted(steps, at - half - 1, side="right"))


@dataclass(frozen=True, slots=True)
class WindowMax:
    """Per row (R,) the window with the largest excess ``rint(Σ counts) − Σ background``
    over the row's S steps (the first of equal ones): ``j`` int64 its centre,
    ``cnt`` float64 its count (an integer), ``mu`` float64 its expected background,
    ``n_positive`` int64 the row's steps with background > 0."""

    j: np.ndarray
    cnt: np.ndarray
    mu: np.ndarray
    n_positive: np.ndarray


def strongest_windows(counts, background, steps, n_steps: int, width: int) -> WindowMax:
    """:class:`WindowMax` of rows whose values at the visited ``steps`` are ``counts``,
    ``background`` (R, U) float64 (zero at the other of ``n_steps``): the numbers of
    ``argmax(rint(moving_sum(counts)) − moving_sum(background))`` over the whole rows."""
    H = np.ascontiguousarray(counts, np.float64)
    B = np.ascontiguousarray(background, np.float64)
    ev = window_events(steps, n_steps, width)
    R = H.shape[0]
    j, npos = np.zeros(R, np.int64), np.zeros(R, np.int64)
    cnt, mu = np.zeros(R), np.zeros(R)
    kernel = compiled_kernel(_window_max_py, _RUNNING) if _loaded() else None
    if kernel is not None and np.isfinite(H).all() and np.isfinite(B).all():
        kernel(H, B, ev.at, ev.a, ev.b, j, cnt, mu, npos)
        return WindowMax(j, cnt, mu, npos)
    rs, rb = _running(H), _running(B)
    sw = np.rint(rs[:, ev.a] - rs[:, ev.b])
    bw = rb[:, ev.a] - rb[:, ev.b]
    k = np.argmax(sw - bw, axis=1)
    rows = np.arange(R)
    return WindowMax(ev.at[k], sw[rows, k], bw[rows, k], np.count_nonzero(B > 0, axis=1))


def _running(x):
    """(R, U + 1) the running sums of the rows ``x`` (R, U), 0 first (np.cumsum's)."""
    out = np.zeros((x.shape[0], x.shape[1] + 1))
    np.cumsum(x, axis=1, out=out[:, 1:])
    return out


def _running_row(H, B, r, rs, rb):  # pragma: no cover - numba
    """``rs[1:]``, ``rb[1:]`` (U + 1,) the running sums of row r of H and B (R, U),
    ``np.cumsum``'s additions in its order (``rs[0]``, ``rb[0]`` stay 0)."""
    U = H.shape[1]
    if U == 0:
        return
    s, b = np.float64(H[r, 0]), np.float64(B[r, 0])
    rs[1], rb[1] = s, b
    for u in range(1, U):
        s = s + H[r, u]
        b = b + B[r, u]
        rs[u + 1], rb[u + 1] = s, b


def _window_max_py(H, B, at, ia, ib, j, cnt, mu, npos):  # pragma: no cover - numba
    """:func:`strongest_windows` row by row (the numba kernel) for finite rows: the
    running sums of a row (``np.cumsum``'s additions), its window sums at the positions
    ``at`` (indices ``ia``, ``ib`` into them) and the first largest excess (as
    ``np.argmax``); writes ``j``, ``cnt``, ``mu``, ``npos`` (R,)."""
    R, U = H.shape
    rs = np.zeros(U + 1)
    rb = np.zeros(U + 1)
    for r in range(R):
        n = 0
        _running_row(H, B, r, rs, rb)
        for u in range(U):
            if B[r, u] > 0:
                n += 1
        best = 0
        bv = np.rint(rs[ia[0]] - rs[ib[0]]) - (rb[ia[0]] - rb[ib[0]])
        for e in range(1, at.shape[0]):
            d = np.rint(rs[ia[e]] - rs[ib[e]]) - (rb[ia[e]] - rb[ib[e]])
            if d > bv:  # (finite values: no NaN to put first)
                best, bv = e, d
        j[r] = at[best]
        cnt[r] = np.rint(rs[ia[best]] - rs[ib[best]])
        mu[r] = rb[ia[best]] - rb[ib[best]]
        npos[r] = n


def visited_excess_band(counts, background, steps, n_steps: int, width: int, rows, j,
                        level: float = 0.5):
    """:func:`~mems_stereo.pipeline.peaks.excess_band` of the rows ``rows`` (Q,) of
    ``counts``, ``background`` (R, U) (values at the visited ``steps``, zero at the
    other of ``n_steps``) around their steps ``j`` (Q,): ``(lo, hi)`` (Q,) int64, the
    same numbers, walking out from ``j`` only as far as the band reaches; None where
    numba is not loaded (then ``excess_band`` of the :func:`dense_rows`)."""
    kernel = compiled_kernel(_band_py, _RUNNING) if _loaded() else None
    if kernel is None:
        return None
    rows = np.asarray(rows, np.int64)
    lo, hi = np.zeros(rows.size, np.int64), np.zeros(rows.size, np.int64)
    kernel(np.ascontiguousarray(counts, np.float64),
           np.ascontiguousarray(background, np.float64), np.asarray(steps, np.int64),
           int(n_steps), int(width) // 2, rows, np.asarray(j, np.int64), float(level), lo, hi)
    return lo, hi


def dense_rows(values, steps, n_steps: int, rows) -> np.ndarray:
    """(Q, ``n_steps``) float64 the rows ``rows`` (Q,) of ``values`` (R, U) laid out over
    all steps (the visited ``steps`` (U,) theirs, zero elsewhere)."""
    out = np.zeros((len(rows), int(n_steps)))
    out[:, np.asarray(steps, np.int64)] = np.asarray(values)[np.asarray(rows, np.int64)]
    return out


def _band_py(H, B, steps, S, half, rows, jr, level, lo_out, hi_out):  # pragma: no cover
    """:func:`visited_excess_band` row by row (the numba kernel): the excess of the
    moving averages (sums over the steps that exist of the window, each divided by
    their number) at j, then position after position to each side until it falls
    below ``level`` times that."""
    U = steps.shape[0]
    rs = np.zeros(U + 1)
    rb = np.zeros(U + 1)
    for k in range(rows.shape[0]):
        r, j = rows[k], jr[k]
        _running_row(H, B, r, rs, rb)
        a0 = np.searchsorted(steps, j + half, side="right")
        b0 = np.searchsorted(steps, j - half - 1, side="right")
        norm = np.float64(min(j + half + 1, S) - max(j - half, 0))
        thr = level * ((rs[a0] - rs[b0]) / norm - (rb[a0] - rb[b0]) / norm)
        a, b, i, lo = a0, b0, j - 1, 0
        while i >= 0:
            while a > 0 and steps[a - 1] > i + half:
                a -= 1
            while b > 0 and steps[b - 1] > i - half - 1:
                b -= 1
            norm = np.float64(min(i + half + 1, S) - max(i - half, 0))
            if (rs[a] - rs[b]) / norm - (rb[a] - rb[b]) / norm < thr:
                lo = i + 1
                break
            i -= 1
        a, b, i, hi = a0, b0, j + 1, S - 1
        while i < S:
            while a < U and steps[a] <= i + half:
                a += 1
            while b < U and steps[b] <= i - half - 1:
                b += 1
            norm = np.float64(min(i + half + 1, S) - max(i - half, 0))
            if (rs[a] - rs[b]) / norm - (rb[a] - rb[b]) / norm < thr:
                hi = i - 1
                break
            i += 1
        lo_out[k] = lo
        hi_out[k] = hi


def visited_window_rows(B, steps, n_steps: int, q, lo, hi):
    """(Q, ``n_steps``) ``scipy.sparse.csr_array`` float64: the rows ``q`` (Q,) of the
    rows whose values at the visited ``steps`` (U,) are ``B`` (P, U) (zero elsewhere),
    over the columns ``lo[i]..hi[i]`` of each: as
    :func:`~mems_stereo.pipeline.peak_table.window_rows` of the dense rows, the same
    matrix, with the values at the visited steps stored (the others are zero)."""
    from scipy.sparse import csr_array

    q, lo, hi = (np.asarray(x, np.int64).ravel() for x in (q, lo, hi))
    steps = np.asarray(steps, np.int64)
    a = np.searchsorted(steps, lo, side="left")
    n = np.maximum(np.searchsorted(steps, hi, side="right") - a, 0)
    indptr = np.zeros(q.size + 1, np.int64)
    np.cumsum(n, out=indptr[1:])
    row = np.repeat(np.arange(q.size), n)
    at = np.arange(indptr[-1]) - indptr[:-1][row] + a[row]  # the visited steps' index
    return csr_array((np.asarray(B)[q[row], at], steps[at], indptr),
                     shape=(q.size, int(n_steps)))


def step_span(background, steps):
    """``(some, first, last)``: per row of ``background`` (R, U) (values at the visited
    ``steps``) whether any is > 0, and the first and last step where it is (int64;
    0 and the last visited step where none)."""
    has = np.asarray(background) > 0
    some = has.any(axis=1)
    steps = np.asarray(steps, np.int64)
    if steps.size == 0:
        return some, np.zeros(has.shape[0], np.int64), np.zeros(has.shape[0], np.int64)
    first = steps[np.argmax(has, axis=1)]
    last = steps[has.shape[1] - 1 - np.argmax(has[:, ::-1], axis=1)]
    return some, first, last


def background_at_steps(lo, hi, shots, rate_hz, bin_width: float) -> np.ndarray:
    """(P, U) float64 C-contiguous:
    :func:`~mems_stereo.physics.background.expected_background_at_steps` of the accepted
    codes ``lo``, ``hi`` (U, P) of U steps with ``shots`` (U,) valid shots, pixels'
    rates ``rate_hz`` (P,) Hz.  Its powers ``(1 − q)^m = exp(m·ln(1 − q))`` are the same
    few per pixel at most steps (a pixel's accepted interval changes slowly with the
    step): where numba is loaded a compiled pass lists each pixel's distinct exponents,
    NumPy's ``exp`` evaluates those alone (the same function on the same numbers: the
    same bits) and a second pass sets the (P, U) values from them."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    kernels = (compiled_if_loaded(_distinct_powers_py), compiled_if_loaded(_from_powers_py))
    if (kernels[0] is None or kernels[1] is None or lo.dtype != np.uint16
            or hi.dtype != np.uint16 or lo.size == 0):
        return np.ascontiguousarray(expected_background_at_steps(lo, hi, shots, rate_hz,
                                                                 bin_width))
    U, P = lo.shape
    m = np.empty(2 * U * P, np.int64)  # (only the first n are written)
    start = np.zeros(P + 1, np.int64)
    top = int(max(lo.max(), hi.max()))
    n = kernels[0](lo, hi, np.full(top + 2, -1, np.int64), m, start)
    a = np.log1p(-np.minimum(-np.expm1(-np.nan_to_num(rate_hz) * bin_width), 1 - 1e-15))
    pix = np.repeat(np.arange(P), np.diff(start))
    powers = np.exp(m[:n].astype(np.float64) * a[pix])
    out = np.empty((P, U))
    kernels[1](lo, hi, powers, m, start, np.full(top + 2, -1, np.int64),
               np.asarray(shots, np.int64), out)
    return out


def _distinct_powers_py(lo, hi, slot, m, start):  # pragma: no cover - numba
    """Per pixel p the distinct exponents ``lo − 1`` and ``hi`` of its steps with
    ``lo <= hi`` (uint16 codes, (U, P)), listed in ``m`` from ``start[p]`` (``start``
    (P + 1,)); ``slot`` (max code + 2,) all −1 on entry and return (exponent e at
    e + 1).  Returns the list's length."""
    U, P = lo.shape
    n = 0
    for p in range(P):
        start[p] = n
        for u in range(U):
            a = np.int64(lo[u, p])
            b = np.int64(hi[u, p])
            if a <= b:
                if slot[a] < 0:  # exponent a − 1
                    slot[a] = n
                    m[n] = a - 1
                    n += 1
                if slot[b + 1] < 0:
                    slot[b + 1] = n
                    m[n] = b
                    n += 1
        for t in range(start[p], n):
            slot[m[t] + 1] = -1
    start[P] = n
    return n


def _from_powers_py(lo, hi, powers, m, start, slot, shots, out):  # pragma: no cover
    """``out[p, u]`` = (powers of ``lo − 1`` − powers of ``hi``) · shots[u], 0 where
    lo > hi: NumPy's ``where(lo <= hi, exp − exp, 0) * shots`` from the list of
    :func:`_distinct_powers_py` (``slot`` as there)."""
    U, P = lo.shape
    for p in range(P):
        for t in range(start[p], start[p + 1]):
            slot[m[t] + 1] = t
        for u in range(U):
            a = np.int64(lo[u, p])
            b = np.int64(hi[u, p])
            d = powers[slot[a]] - powers[slot[b + 1]] if a <= b else 0.0
            out[p, u] = d * np.float64(shots[u])
        for t in range(start[p], start[p + 1]):
            slot[m[t] + 1] = -1


#: the helper of the kernels above (:func:`compiled_kernel` binds the name to its
#: compiled form)
_RUNNING = {"_running_row": _running_row}
