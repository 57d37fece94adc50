"""The peak detector's neighbour support: a peak that no neighbour on the same surface
supports must pass the sensor's per-frame threshold.

A dense surface images onto neighbouring pixels, while a background false alarm is
isolated: :func:`supported` keeps a peak when another peak within
:data:`SUPPORT_COLUMNS` lies at an agreeing range (:func:`neighbour_support`,
:func:`support_ranges`) or when its window count passes :func:`frame_threshold`,
the scan statistics (:func:`scan_sf`) of the sliding window at
:data:`FRAME_FALSE_ALARMS` false peaks per recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.uncertainty import stereo_point_est
from mems_stereo.model.system import System

#: false peaks per frame (one recording, the whole sensor) allowed among the peaks that
#: no neighbour on the same surface supports (:func:`supported`): at the per-pixel
#: level (``Settings.false_alarm``, more with the sliding window's clumping) a sensor
#: of a few hundred pixels gets a false peak in about every second frame, and next to a
#: sparse surface (a few peaks) that one false point is a large share of the cloud
FRAME_FALSE_ALARMS = 0.01


def scan_sf(k, mu, n_windows) -> np.ndarray:
    """P(the largest sliding-window count of a scan reaches ``k``), background alone.

    ``k``, ``mu``, ``n_windows`` : broadcastable; ``mu`` the window's expected
    background, ``n_windows`` the scan's length in windows.  The first-order
    Poisson clumping (Naus–Alm) approximation
    ``P(X ≥ k) + (n_windows − 1)·(k − mu)·p(k; mu)`` for ``k > mu``: the expected
    number of upcrossings of ``k`` by a window sliding over background (a point
    entering while the window holds k − 1 and none leaving) — ``k − mu`` times the
    Bonferroni term ``p(k)`` per window position (about ``k`` times it at low
    background, ``z²`` at high).  Clipped to [0, 1].
    """
    from scipy.special import pdtrc

    k, mu, nw = np.broadcast_arrays(np.asarray(k, np.float64), np.asarray(mu, np.float64),
                                    np.asarray(n_windows, np.float64))
    tail = pdtrc(k - 1, mu)
    pk = tail - pdtrc(k, mu)
    return np.clip(tail + np.maximum(nw - 1, 0) * np.maximum(k - mu, 0) * pk, 0.0, 1.0)


def scan_isf(alpha, mu, n_windows) -> np.ndarray:
    """Smallest integer t with :func:`scan_sf` (t + 1, mu, n_windows) ≤ ``alpha`` (the
    count must exceed t), vectorised; bisection above ``mu`` (where the tail falls)."""
    a, m, nw = np.broadcast_arrays(np.asarray(alpha, np.float64), np.asarray(mu, np.float64),
                                   np.asarray(n_windows, np.float64))
    lo = np.floor(m) - 1.0  # scan_sf(lo + 1) > alpha (for alpha < ~0.5)
    hi = np.ceil(m + 40.0 * np.sqrt(m) + 80.0)  # scan_sf(hi + 1) <= alpha
    while np.any(hi - lo > 1):
        mid = np.floor(0.5 * (lo + hi))
        ok = scan_sf(mid + 1, m, nw) <= a
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid)
    return hi


def frame_threshold(n_windows, mu, n_pixels: int) -> np.ndarray:
    """(P,) the count a peak that its neighbours do not support well must exceed: the
    scan threshold (:func:`scan_isf`) at :data:`FRAME_FALSE_ALARMS` / ``n_pixels``, so
    that background puts such a peak anywhere on the sensor at most
    :data:`FRAME_FALSE_ALARMS` times per recording."""
    return scan_isf(FRAME_FALSE_ALARMS / n_pixels, np.maximum(mu, 1e-12), n_windows)


def supported(keep, cnt, thr_frame, log_range, width: int) -> np.ndarray:
    """(P,) bool: the peaks ``keep`` (P,) of the whole sensor (rows of ``width``) that a
    neighbour on the same surface supports (:func:`neighbour_support` within
    :data:`SUPPORT_COLUMNS`, ``log_range`` (P, 3) :func:`support_ranges`, (P,) or
    None) or that pass the per-frame threshold ``thr_frame`` (P,) with their window
    count ``cnt``."""
    keep = np.asarray(keep, bool)
    return keep & (neighbour_support(keep, width, SUPPORT_COLUMNS, log_range) | (cnt > thr_frame))


#: columns either side of a peak (and rows either side, for an array sensor) in which
#: another peak supports it (:func:`neighbour_support`, the matched filter's chains):
#: a surface that the detector sees in one pixel in several (weak returns, sparse
#: coverage) still has a detected pixel within this reach
SUPPORT_COLUMNS = 8
#: the most by which the ranges of a peak and a supporting neighbour may differ (a
#: factor; stereo range at each peak's window centre): one surface, or an object and
#: the wall behind it, not a near-range background cluster under a far scene
SUPPORT_RANGE_RATIO = 2.0




def neighbour_support(keep, width: int, reach: int = SUPPORT_COLUMNS,
                      log_range=None, ratio: float = None, count: bool = False) -> np.ndarray:
    """(P,) bool: pixels with another ``keep`` pixel within ``reach`` columns in their
    row or, for an array sensor (P > width), within ``reach`` columns in the rows
    ``reach`` above or below.  ``keep`` : (P,) bool over the pixels of rows of
    ``width`` columns (flat index ``row·width + col``).  ``log_range`` : (P,)
    optional log of each peak's range, or (P, 3) :func:`support_ranges` (log range,
    its resolution, the slope allowance per pixel): then only a neighbour whose log
    range is within the two peaks' resolutions plus the slope allowance times their
    distance in pixels, and within a factor ``ratio`` (default
    :data:`SUPPORT_RANGE_RATIO`), supports (a non-finite range is compatible with
    any).  ``count`` : return (P,) int64, the
    number of such neighbours, instead."""
    ratio = SUPPORT_RANGE_RATIO if ratio is None else float(ratio)
    k = np.asarray(keep, bool).reshape(-1, int(width))
    H, W = k.shape
    R = int(reach)
    lr3 = np.zeros((H * W, 3))
    lr3[:, 1:] = np.inf  # no range: compatible with any
    if log_range is not None:
        a = np.asarray(log_range, np.float64)
        if a.ndim == 1:
            lr3[:, 0] = a
        else:
            lr3[:, :a.shape[1]] = a
    lr3 = lr3.reshape(H, W, 3)
    pad_k = np.zeros((H + 2 * R, W + 2 * R), bool)
    pad_k[R:R + H, R:R + W] = k
    pad_r = np.full((H + 2 * R, W + 2 * R, 3), np.nan)
    pad_r[R:R + H, R:R + W] = lr3
    tol = np.log(ratio)
    out = np.zeros((H, W), np.int64)
    rows = range(-R, R + 1) if H > 1 else (0,)
    for dr in rows:
        for dc in range(-R, R + 1):
            if dr == 0 and dc == 0:
                continue
            nk = pad_k[R + dr:R + dr + H, R + dc:R + dc + W]
            nr = pad_r[R + dr:R + dr + H, R + dc:R + dc + W]
            # each peak's own range resolution and the surface's slope over the pixels
            # between them, at most the factor ``ratio``
            t = np.minimum(tol, lr3[..., 1] + nr[..., 1]
                           + 0.5 * (lr3[..., 2] + nr[..., 2]) * max(abs(dr), abs(dc)))
            with np.errstate(invalid="ignore"):
                same = ~(np.abs(nr[..., 0] - lr3[..., 0]) > t)  # NaN: compatible
            out += nk & same
    out = out.reshape(-1)
    return out if count else out > 0


#: the steepest incidence (degrees) a supporting neighbour's surface may have: the
#: log range may change by tan(SUPPORT_INCIDENCE_DEG) / fx per pixel between them
SUPPORT_INCIDENCE_DEG = 75.0


def support_ranges(system: System, table, pix, j, width: int) -> np.ndarray:
    """(N, 3) for flat pixels ``pix`` (N,) with peaks centred at steps ``j`` (N,): the
    log stereo range at ``j`` (:func:`pixel_log_range`); its resolution, the largest
    change of the log range within half a footprint (``width`` steps) of ``j`` (a
    window's centre lies within that of the spot's crossing); and the log range's
    change per pixel on a surface at :data:`SUPPORT_INCIDENCE_DEG` (``tan / fx``).
    Non-finite entries (no range) become inf: compatible with any."""
    j = np.asarray(j, np.int64)
    h = int(width) // 2
    lr = pixel_log_range(system, table, pix, j)
    lo = pixel_log_range(system, table, pix, np.maximum(j - h, 0))
    hi = pixel_log_range(system, table, pix, np.minimum(j + h, table.n_steps - 1))
    with np.errstate(invalid="ignore"):
        res = np.maximum(np.abs(hi - lr), np.abs(lo - lr))
    res = np.where(np.isfinite(res), res, np.inf)
    fx = float(system.receiver.camera_matrix[0, 0])
    slope = np.full(lr.shape, np.tan(np.radians(SUPPORT_INCIDENCE_DEG)) / fx)
    return np.stack([lr, res, slope], axis=1)


def pixel_log_range(system: System, table, pix, j) -> np.ndarray:
    """(N,) log of the stereo range of flat pixels ``pix`` (N,) at the angles of steps
    ``j`` (N,) of ``table`` (NaN where the rays do not meet in front)."""
    pix = np.asarray(pix, np.int64)
    W = system.receiver.width
    x = stereo_point_est(system, (pix % W).astype(np.float64), (pix // W).astype(np.float64),
                         np.zeros(pix.size), table.theta_min + np.asarray(j) * table.step)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.log(np.linalg.norm(x, axis=1))


@dataclass(frozen=True, slots=True)
class SupportInputs:
    """What :func:`supported` needs of a block of pixels' scores, and their background rate.

    keep : (Pb,) bool, the pixels' peaks before the neighbour support; cnt : (Pb,)
    float64, their strongest window's count; thr_frame : (Pb,) float64, the per-frame
    threshold (:func:`frame_threshold`); log_range : (Pb, 3) float64,
    :func:`support_ranges` at the window's centre; rate : (Pb,) float64 Hz, the pixels'
    ML background rate.  Blocks of consecutive pixels join with :meth:`concat`.
    """

    keep: np.ndarray
    cnt: np.ndarray
    thr_frame: np.ndarray
    log_range: np.ndarray
    rate: np.ndarray

    @classmethod
    def concat(cls, parts) -> SupportInputs:
        """The inputs of consecutive blocks of pixels, in order, as one."""
        parts = list(parts)
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("keep", "cnt", "thr_frame", "log_range", "rate")))

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays."""
        return sum(getattr(self, f).nbytes
                   for f in ("keep", "cnt", "thr_frame", "log_range", "rate"))

    def supported(self, width: int) -> np.ndarray:
        """(Pb,) bool: :func:`supported` of these pixels (a whole sensor of rows of
        ``width`` columns)."""
        return supported(self.keep, self.cnt, self.thr_frame, self.log_range, width)
