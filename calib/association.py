"""Background-aware association: which (shot, pixel) cells the fit analyses.

Nothing is decided per shot.  Each pixel's background rate is measured in the
late part of the TDC window (after ``late_start``, where no wall return can
be) by the first-photon maximum-likelihood estimate
``λ = −ln(1 − n_fired / n_armed) / (T_window − late_start)``
(:func:`background_rates`); the cells of a wall are then all pixels within
``radius`` of the beam's predicted image for every shot
(:func:`cells_near_track`), whatever fired there: the likelihood of
:mod:`.problem` weighs signal against that known background.
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib.problem import Cells, WallData

from mems_stereo.model.scanner import phase_from_zero_crossings

#: TDC time after which a wall return is not expected (background only), s:
#: walls up to about 25 m
LATE_START = 250e-9
#: pseudo-counts pulling a pixel's background rate towards the recording's mean
POOL_WEIGHT = 20.0


def background_rates(bins: np.ndarray, bin_width: float, n_bins: int,
                     late_start: float = LATE_START) -> np.ndarray:
    """(H, W) background rate of each pixel, Hz, from codes after ``late_start``.

    A pixel is armed at ``late_start`` in the shots where it has not fired
    before; of those, the share that fire before the window's end gives λ.
    Each pixel's count is shrunk towards the recording's mean rate by
    ``POOL_WEIGHT`` pseudo-counts (a pixel with few late detections borrows
    from its neighbours).  bins : (K, H, W) uint16.
    """
    window = n_bins * bin_width
    n0 = int(np.floor(late_start / bin_width)) + 1  # first code at or after late_start
    if n0 >= n_bins:
        raise ValueError(f"late_start {late_start * 1e9:.0f} ns: expected inside the TDC "
                         f"window ({window * 1e9:.0f} ns)")
    fired_late = bins >= n0
    armed = (bins == 0) | fired_late
    n_f = fired_late.sum(axis=0).astype(np.float64)
    n_a = armed.sum(axis=0).astype(np.float64)
    span = window - (n0 - 1) * bin_width
    p_pool = n_f.sum() / max(n_a.sum(), 1.0)
    p = (n_f + POOL_WEIGHT * p_pool) / (n_a + POOL_WEIGHT)
    p = np.clip(p, 0.0, 1.0 - 1e-9)
    return -np.log1p(-p) / span


def wall_data(recording, late_start: float = LATE_START) -> WallData:
    """:class:`WallData` of a :class:`~mems_stereo.io.recording.Recording`
    (shots with a known monitor phase only)."""
    from mems_stereo.errors import FormatError

    ph, ok = phase_from_zero_crossings(recording.shot_time, recording.zero_crossings,
                                       recording.rising)
    ok = np.asarray(ok, dtype=bool) & np.isfinite(ph)
    if not ok.any():
        raise FormatError("expected shots with a known mirror phase, found none (no "
                          "zero crossings around the shots?)", recording.source,
                          "/monitor/zero_crossings")
    bins = np.asarray(recording.bins)[ok]
    tdc = recording.system.tdc
    lam = background_rates(bins, tdc.bin_width, tdc.n_bins, late_start)
    return WallData(np.asarray(ph, dtype=np.float64)[ok], bins, lam, tdc.bin_width,
                    recording.source, np.asarray(recording.shot_time, dtype=np.float64)[ok],
                    np.asarray(recording.zero_crossings, dtype=np.float64),
                    np.asarray(recording.rising, dtype=bool))


def cells_near_track(w: WallData, pred: np.ndarray, ok: np.ndarray, radius: int,
                     t_max: float, log_gref: float, two_d: bool) -> Cells:
    """All pixels within ``radius`` of each shot's predicted image.

    pred : (K, 4) per-shot [τ, u, v, log g] (:func:`mems_stereo.calib.problem.shot_model`);
    ok : (K,) the beam meets the wall.  Shots whose image lies farther than
    ``radius`` outside the sensor give no cells.  Codes later than ``t_max``
    count as "not fired by t_max".
    """
    K, H, W = w.bins.shape
    u, v = pred[:, 1], pred[:, 2]
    good = ok & (u > -radius - 0.5) & (u < W - 0.5 + radius)
    if two_d:
        good &= (v > -radius - 0.5) & (v < H - 0.5 + radius)
    shots = np.flatnonzero(good)
    off = np.arange(-radius, radius + 1)
    cu = np.rint(u[shots])[:, None] + off[None, :]
    if two_d:
        cv = np.rint(v[shots])[:, None] + off[None, :]
        cols = np.broadcast_to(cu[:, None, :], (shots.size, off.size, off.size)).reshape(
            shots.size, -1)
        rows = np.broadcast_to(cv[:, :, None], (shots.size, off.size, off.size)).reshape(
            shots.size, -1)
    else:
        cols = cu
        rows = np.zeros_like(cu)
    sh = np.broadcast_to(shots[:, None], cols.shape)
    inside = (cols >= 0) & (cols < W) & (rows >= 0) & (rows < H)
    sh, cols, rows = sh[inside], cols[inside].astype(np.int64), rows[inside].astype(np.int64)
    code = w.bins[sh, rows, cols]
    if w.code_centres is None:
        t = (code.astype(np.float64) - 0.5) * w.bin_width
    else:  # the TDC's measured code widths (DNL/INL): each code's centre
        t = np.asarray(w.code_centres, dtype=np.float64)[np.maximum(code.astype(np.int64), 1)
                                                          - 1]
    t = np.where((code > 0) & (t <= t_max), t, np.nan)
    return Cells(sh.astype(np.int64), cols.astype(np.float64), rows.astype(np.float64), t,
                 w.background[rows, cols], float(t_max), shots.astype(np.int64),
                 float(log_gref))
