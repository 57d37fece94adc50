"""The mean shot time of each frame point's counted detections, in one compiled loop.

:func:`~mems_stereo.pipeline.frames.point_times` stamps each point with the mean time
of the shots whose detection in its pixel its peak's pass 2 counted.  NumPy gathers a
(shots, points) block of codes and tests it against five bounds; :func:`shot_time_sums`
tests each (point, shot) once, without the temporaries (a numba kernel, made where
numba is imported: the frames' processor loads it).
"""

from __future__ import annotations

import numpy as np

from mems_stereo.util.lazy_numba import compiled_if_loaded


def shot_time_sums(bins, known, tk, sk, peaks, q, lo_hi):
    """``(sums, counts)`` (n,) float64 and int64, or None where numba is not imported.

    bins : (K, H, W) uint16 the frame's codes; known : (K',) int64 the shots with a
    table row; tk : (K',) float64 their times (s, from any origin); sk : (K',) int64
    their table rows (angle steps); peaks : the run's
    :class:`~mems_stereo.pipeline.peak_table.Peaks`; q : (n,) int64 the points'
    peaks; lo_hi : ``(lo, hi)`` (S, H·W) the interval table's accepted codes.
    For each point, over the shots whose code in its pixel lies in its peak's code
    window and in the table's accepted interval at the shot's step, and whose step lies
    in the peak's band: the sum of their times and their number."""
    kernel = compiled_if_loaded(_time_sums_py)
    if kernel is None:
        return None
    q = np.asarray(q, np.int64)

    def take(a):
        return np.ascontiguousarray(np.asarray(a)[q], np.int64)

    bounds = np.stack([take(peaks.code_lo), take(peaks.code_hi), take(peaks.step_lo),
                       take(peaks.step_hi)])
    return kernel(bins, np.asarray(known, np.int64), np.asarray(tk, np.float64),
                  np.asarray(sk, np.int64), take(peaks.row), take(peaks.col), bounds,
                  lo_hi[0], lo_hi[1])


def _time_sums_py(bins, known, tk, sk, rows, cols, bounds, lo,
                  hi):  # pragma: no cover - compiled by numba
    """:func:`shot_time_sums`' loop: ``bounds`` (4, n) the code window (lo, hi) and the
    band (step_lo, step_hi) of each point's peak."""
    n = rows.size
    W = bins.shape[2]
    sums = np.zeros(n)
    counts = np.zeros(n, np.int64)
    for i in range(n):
        r, c = rows[i], cols[i]
        pix = r * W + c
        c_lo, c_hi, s_lo, s_hi = bounds[0, i], bounds[1, i], bounds[2, i], bounds[3, i]
        for k in range(known.size):
            st = sk[k]
            if st < s_lo or st > s_hi:
                continue
            code = np.int64(bins[known[k], r, c])
            if code < c_lo or code > c_hi or code < lo[st, pix] or code > hi[st, pix]:
                continue
            sums[i] += tk[k]
            counts[i] += 1
    return sums, counts
