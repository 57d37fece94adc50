"""Expected background among a peak's counted detections, per (peak, angle step).

:func:`window_background` turns pass 2's counts of one (peak, step) into the
background those shots recorded (a SPAD pixel records one photon per shot:
background is recorded only by shots not yet fired), spread over segments
of the accepted code interval; the fusion subtracts it as negative-weight
entries (:func:`mems_stereo.pipeline.fusion.peak_sums_from_counts`).
"""

from __future__ import annotations

import numpy as np

#: segments of each (peak, step)'s accepted code interval over which its expected
#: background is spread (as negative-weight entries at the segments' centroids)
BACKGROUND_SEGMENTS = 8


def window_background(group, code, count, a, b, n_shots, lo, rate_hz, bin_width,
                      segments: int = BACKGROUND_SEGMENTS):
    """Expected background detections among the counted codes of each (peak, angle step).

    A SPAD pixel records one photon per shot, so background can only be
    recorded by shots that have not fired yet: with the hazard
    ``h = 1 − exp(−λ·Δt)`` per bin, the expected background in code c is
    ``h·S(c)``, S(c) the shots of the step still unfired at c — the shots that
    reach the accepted interval unfired (``n·(1 − h)^(lo−1)``) less the
    detections counted at the codes before c (a martingale: exact in
    expectation whatever the signal).  Where the laser fires the pixel in
    most shots this is far below the free-running expectation, and it is not
    uniform in code: background before the return is recorded, after it
    mostly not — subtracting it as a uniform share would bias both the signal
    level (hence the first-photon correction) and the time of flight early.

    Parameters (one entry per distinct (group, code), sorted by group, then code)
    ----------
    group : (M,) int, the (peak, step) group; code : (M,) int TDC code;
    count : (M,) detections; a, b : (M,) the group's counted codes (its
    accepted interval ∩ the peak's code window); n_shots : (M,) valid shots of
    the step; lo : (M,) start of the accepted interval; rate_hz : (M,) λ.

    Returns
    -------
    first : (G,) index of each group's first entry;
    bg : (G, J) expected background of each of the J segments of [a, b];
    centroid : (G, J) its mean code (float64).
    """
    group = np.asarray(group, np.int64)
    code = np.asarray(code, np.float64)
    cnt = np.asarray(count, np.float64)
    _, first, inv = np.unique(group, return_index=True, return_inverse=True)
    G = first.size
    h = -np.expm1(-np.nan_to_num(np.asarray(rate_hz, np.float64)[first]) * bin_width)
    s0 = np.asarray(n_shots, np.float64)[first] * np.exp(
        (np.asarray(lo, np.float64)[first] - 1.0) * np.log1p(-np.minimum(h, 1 - 1e-15)))
    ag = np.asarray(a, np.float64)[first]
    bg_ = np.asarray(b, np.float64)[first]
    n_codes = np.maximum(bg_ - ag + 1.0, 0.0)
    J = int(segments)
    edges = ag[:, None] + np.floor(n_codes[:, None] * np.arange(J + 1)[None, :] / J)
    s_lo, s_hi = edges[:, :-1], edges[:, 1:] - 1.0  # (G, J) inclusive
    length = np.maximum(s_hi - s_lo + 1.0, 0.0)

    def csum(m, n):  # Σ c for c = m..n (0 when n < m)
        return np.where(n >= m, (m + n) * (n - m + 1.0) / 2.0, 0.0)

    tot = s0[:, None] * length
    tot_c = s0[:, None] * csum(s_lo, s_hi)
    ce1 = code + 1.0
    closed = np.zeros((G, J))
    closed_c = np.zeros((G, J))
    for j in range(J):  # one segment at a time: (M,) temporaries, no (M, J)
        start = np.maximum(s_lo[inv, j], ce1)  # codes of the segment after the detection
        hi_j = s_hi[inv, j]
        m = np.maximum(hi_j - start + 1.0, 0.0)
        closed[:, j] = np.bincount(inv, weights=cnt * m, minlength=G)
        closed_c[:, j] = np.bincount(inv, weights=cnt * csum(start, hi_j), minlength=G)
    S_sum = np.maximum(tot - closed, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = np.where(S_sum > 0, (tot_c - closed_c) / S_sum, 0.5 * (s_lo + s_hi))
    return first, h[:, None] * S_sum, centroid
