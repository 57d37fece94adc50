"""Acceptance counts: per pixel and TDC code, the valid shots whose accepted code
interval (the interval table's, at the shot's angle step) holds the code — what the
background rate of the noise histogram needs to know of the classifier
(:func:`~mems_stereo.physics.background.background_rate_from_noise`).
"""

from __future__ import annotations

import numpy as np

from mems_stereo.model.system import System
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.util.lazy_numba import compiled_if_loaded


def acceptance_counts(system: System, theta, valid, confidence: float,
                      min_range: float | None = None, table=None,
                      n_per_step=None, pixels=None) -> np.ndarray:
    """A[p, j]: valid shots in which code j+1 of pixel p was accepted as signal.

    (P, n_bins) int64, from the interval table and the shots' angle steps (a
    difference array over codes: O(steps × pixels), not O(shots × pixels)).
    ``table`` : the run's interval table (default: a new one); ``n_per_step``
    : (S,) valid shots per step (default: counted from ``theta``, ``valid``);
    ``pixels`` : (P,) flat pixels (default: all, in order).
    """
    if table is None:
        table = interval_table(system, confidence, min_range=min_range)
    n_per_row = (table.shots_per_step(theta, valid) if n_per_step is None
                 else np.asarray(n_per_step))
    used = np.flatnonzero(n_per_row)
    n_row = n_per_row[used]
    table.ensure(used)
    n_bins = system.tdc.n_bins
    pix = (np.arange(table.lo.shape[1]) if pixels is None
           else np.asarray(pixels, np.int64))
    kernel = compiled_if_loaded(_acceptance_py)
    if kernel is not None:  # integer sums: the same numbers in any order
        return kernel(table.lo, table.hi, used.astype(np.int64), pix,
                      n_row.astype(np.int64), n_bins)
    sel = used if pixels is None else np.ix_(used, pix)
    lo = table.lo[sel].astype(np.int64)  # (U, P)
    hi = table.hi[sel].astype(np.int64)
    ok = lo <= hi
    P = lo.shape[1]
    w = np.broadcast_to(n_row[:, None], lo.shape)[ok].astype(np.float64)
    at = np.broadcast_to(np.arange(P)[None, :] * (n_bins + 2), lo.shape)[ok]
    # the difference array by bincount (float sums of integers below 2**53: exact)
    diff = (np.bincount(at + lo[ok], w, P * (n_bins + 2))
            - np.bincount(at + hi[ok] + 1, w, P * (n_bins + 2)))
    diff = np.rint(diff).astype(np.int64).reshape(P, n_bins + 2)
    return np.cumsum(diff, axis=1)[:, 1:n_bins + 1]


def _acceptance_py(lo, hi, used, pix, n_row, n_bins):  # pragma: no cover - numba
    """:func:`acceptance_counts` loop by loop (the numba kernel): ``lo``, ``hi`` (S, P')
    the interval table's accepted codes, ``used`` (U,) the steps with shots, ``pix`` (P,)
    the pixels, ``n_row`` (U,) int64 each used step's valid shots; returns (P, n_bins)
    int64, per pixel the difference array over codes summed (integers: exact)."""
    U, P = used.shape[0], pix.shape[0]
    diff = np.zeros(n_bins + 2, np.int64)  # one pixel's, in cache
    out = np.empty((P, n_bins), np.int64)
    for p in range(P):
        diff[:] = 0
        q = pix[p]
        for u in range(U):
            a = np.int64(lo[used[u], q])
            b = np.int64(hi[used[u], q])
            if a <= b:
                diff[a] += n_row[u]
                diff[b + 1] -= n_row[u]
        acc = diff[0]
        for c in range(1, n_bins + 1):
            acc += diff[c]
            out[p, c - 1] = acc
    return out
