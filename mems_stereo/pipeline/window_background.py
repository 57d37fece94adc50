"""Expected background among a peak's counted detections, per (peak, angle step).

:func:`window_background` turns pass 2's counts of one (peak, step) into the
background those shots recorded (a SPAD pixel records one photon per shot:
background is recorded only by shots not yet fired), spread over segments
of the accepted code interval; the fusion subtracts it as negative-weight
entries (:func:`mems_stereo.pipeline.fusion.peak_sums_from_counts`).
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.pipeline.classify_kernel import compiles
from mems_stereo.util.lazy_numba import compiled_if_loaded

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
    first, inv = _groups(group)
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
    closed = np.zeros((G, J))
    closed_c = np.zeros((G, J))
    kernel = compiled_if_loaded(_closed_py) if compiles(inv.size, COMPILED_ENTRIES) else None
    if kernel is not None:  # the loop below in one compiled pass over the entries
        kernel(inv, code, cnt, np.ascontiguousarray(s_lo), np.ascontiguousarray(s_hi),
               closed, closed_c)
    else:
        ce1 = code + 1.0
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


#: entries from which :func:`window_background` runs its per-entry loop compiled (where
#: numba is loaded already: a dense run's pass 1 loaded it)
COMPILED_ENTRIES = 4096


def _groups(group):
    """``(first, inv)`` of ``np.unique(group, return_index=True, return_inverse=True)``:
    in one pass where ``group`` is sorted (the fusion's entries are), else by
    ``np.unique``."""
    if group.size and bool(np.all(group[1:] >= group[:-1])):
        new = np.empty(group.size, bool)
        new[0] = True
        np.not_equal(group[1:], group[:-1], out=new[1:])
        return np.flatnonzero(new), np.cumsum(new) - 1
    _, first, inv = np.unique(group, return_index=True, return_inverse=True)
    return first, inv


def _closed_py(inv, code, cnt, s_lo, s_hi, closed, closed_c):
    """Per entry i of group g = inv[i] and segment j: the counted detections' closed
    share of the segment's codes after them, added to ``closed[g, j]`` and
    ``closed_c[g, j]`` (zeros on entry) in entry order — the same IEEE operations
    in the same order as :func:`window_background`'s NumPy loop (``np.bincount``
    adds its weights in input order from 0.0), so the same bits."""
    J = s_lo.shape[1]
    for i in range(inv.shape[0]):
        g = inv[i]
        ce1 = code[i] + 1.0
        c = cnt[i]
        for j in range(J):
            lo = s_lo[g, j]  # start = np.maximum(lo, ce1): NaN if either is
            start = (lo if math.isnan(lo) else ce1 if math.isnan(ce1)
                     else lo if lo >= ce1 else ce1)
            hi = s_hi[g, j]
            m = hi - start + 1.0
            m = m if math.isnan(m) or m >= 0.0 else 0.0  # np.maximum(m, 0.0)
            closed[g, j] += c * m
            cs = (start + hi) * (hi - start + 1.0) / 2.0 if hi >= start else 0.0
            closed_c[g, j] += c * cs


#: nodes (equally spaced codes, ends included) at which :func:`inlier_codes`
#: evaluates each group's inlier margins before its secant refinement
INLIER_NODES = 9


def inlier_codes(margins, a, b, nodes: int = INLIER_NODES, refine: int = 2):
    """The codes ``[c1, c2]`` of ``[a, b]`` whose entries pass a peak's inlier test.

    The inlier test of a (peak, step) keeps an entry when its range lies
    within the bound about the peak's centre; at one step the range grows with
    the code, so the kept codes are one interval.  The expected background
    must be subtracted over exactly those codes: spread over segments of the
    whole accepted interval and tested at the segments' centroids, a segment
    of hundreds of codes (a pixel whose interval reaches the beam's vanishing
    point holds all 4096) is kept or dropped whole, while the inlier window is
    ± a few pulse widths — the background under the return was left in or
    taken from elsewhere, and the time of flight of faint returns under strong
    background came out up to a metre early.

    ``margins(g, c)`` : for group indices g (N,) and float codes c (N,) returns
    ``(f_lo, f_hi)`` (N,): range − (centre − bound) and (centre + bound) −
    range (both ≥ 0 inside; f_lo increasing, f_hi decreasing in the code; NaN
    where not evaluable).  ``a, b`` : (G,) the groups' counted codes.  The
    crossings are found by linear interpolation between ``nodes`` equally
    spaced codes, then ``refine`` secant steps.  Returns (G,) float64 ``c1, c2``
    (c1 > c2: no inlier code); a group with a NaN margin keeps ``[a, b]``.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    G = a.size
    t = np.linspace(0.0, 1.0, int(nodes))
    c = a[:, None] + (b - a)[:, None] * t[None, :]  # (G, n)
    g = np.repeat(np.arange(G), t.size)
    f_lo, f_hi = (x.reshape(G, t.size) for x in margins(g, c.ravel()))
    bad = ~(np.all(np.isfinite(f_lo), axis=1) & np.all(np.isfinite(f_hi), axis=1))
    c1 = _crossing(margins, c, f_lo, a, b, rising=True, refine=refine, which=0)
    c2 = _crossing(margins, c, f_hi, a, b, rising=False, refine=refine, which=1)
    c1 = np.where(bad, a, c1)
    c2 = np.where(bad, b, c2)
    return c1, c2


def _crossing(margins, c, f, a, b, rising, refine, which):
    """Code where the monotone margin f (G, n) at codes c crosses 0 (see
    :func:`inlier_codes`): the first inside code (``rising``) or the last."""
    G, n = f.shape
    inside = f >= 0
    out = np.empty(G)
    if rising:  # inside from the crossing on
        all_in, none_in = inside[:, 0], ~inside[:, -1]
        j = np.argmax(inside, axis=1)  # first inside node
        i0, i1 = np.maximum(j - 1, 0), j
        out[:] = np.where(all_in, a, np.where(none_in, np.inf, np.nan))
    else:  # inside up to the crossing
        all_in, none_in = inside[:, -1], ~inside[:, 0]
        j = n - 1 - np.argmax(inside[:, ::-1], axis=1)  # last inside node
        i0, i1 = j, np.minimum(j + 1, n - 1)
        out[:] = np.where(all_in, b, np.where(none_in, -np.inf, np.nan))
    todo = np.flatnonzero(np.isnan(out))
    r = np.arange(G)[todo]
    x0, x1 = c[r, i0[todo]], c[r, i1[todo]]
    y0, y1 = f[r, i0[todo]], f[r, i1[todo]]
    for it in range(refine + 1):
        with np.errstate(invalid="ignore", divide="ignore"):
            x = np.where(y1 != y0, x0 - y0 * (x1 - x0) / (y1 - y0), 0.5 * (x0 + x1))
        x = np.clip(np.nan_to_num(x, nan=0.5), np.minimum(x0, x1), np.maximum(x0, x1))
        if it == refine or not todo.size:
            break
        y = margins(todo, x)[which]
        y = np.where(np.isfinite(y), y, 0.0)
        same = (y >= 0) == (y0 >= 0)  # keep the bracket: replace the end on y's side
        x0, y0 = np.where(same, x, x0), np.where(same, y, y0)
        x1, y1 = np.where(same, x1, x), np.where(same, y1, y)
    out[todo] = x
    return out
