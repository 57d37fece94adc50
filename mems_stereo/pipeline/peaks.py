"""The peak detector: per pixel, where its signal detections cluster in scan angle.

After classification each pixel has, from pass 1, its signal detections per
scan-angle step of the interval table (``hist_angle``) and its noise
histogram N.  The background that passed the classifier is known exactly
per step: the valid shots of the step times the probability that
background alone produced a first photon inside the step's accepted code
interval, ``(1 − q)^(lo−1) − (1 − q)^hi`` with ``q = λ·Δt`` and λ the
pile-up-aware maximum-likelihood background rate of N
(:func:`mems_stereo.physics.background.background_rate_from_noise`).
:func:`find_peaks` slides a window of one pixel footprint over the steps,
takes the largest excess over that expectation and keeps it when the
window count exceeds the Poisson quantile of the background at
``Settings.false_alarm`` per pixel (spread over the independent window
positions): a likelihood-ratio test of "return here" against "background
only" with the background known per (step, code interval).  Result: a
typed :class:`Peaks`.  (The paper's detector on the code histogram is kept
as a test oracle, tests/oracles.py.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.uncertainty import stereo_point_est
from mems_stereo.model.system import System
from mems_stereo.physics.background import (
    background_rate_from_noise,
    expected_background_by_angle,
    moving_sum,
    poisson_isf,
)
from mems_stereo.pipeline.histograms import moving_average
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.settings import Settings


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
    sel = used if pixels is None else np.ix_(used, np.asarray(pixels, np.int64))
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


def strongest_window(counts, background, width: int, support, settings: Settings,
                     support_pixels: tuple | None = None):
    """Per row, the window of ``width`` bins with the largest excess over the background.

    ``counts``, ``background`` : (P, B) observed and expected counts;
    ``support`` : (P, B) bool, where background can occur at all (the number
    of independent window positions is its count / width: the false-alarm
    probability ``settings.false_alarm`` is per row, spread over them —
    Bonferroni over disjoint windows; the largest of a window sliding one step
    at a time exceeds it more often, by about the window count at low
    background, see docs/pipeline.md).  Window sums are exact: integer counts,
    no rescaling at the ends of the rows (a float sum of 7 read as
    7.000000000000001 passed a threshold of 7).
    ``support_pixels`` : ``(width, n_pixels)`` or ``(width, n_pixels, log_range_of)``
    of the sensor whose pixels the rows are (flat ``row·width + col``;
    ``log_range_of(j)`` : (P,) the log range of each row's peak at its window
    centres ``j`` (P,)), or None.
    With it a peak that no neighbour on the same surface supports
    (:func:`neighbour_support`: none within :data:`SUPPORT_COLUMNS` at an agreeing
    range) must also pass the sensor's per-frame threshold (:func:`frame_threshold`:
    :data:`FRAME_FALSE_ALARMS` false peaks per recording, scan statistics of the
    sliding window): a dense surface images onto
    neighbouring pixels, while a background false alarm is isolated or sits next to
    a sparse surface, whose few peaks would lend it their support.
    Returns ``(j, count, mu, keep)``, each (P,): the window's centre index, its
    count and expected background, and whether it passes the Poisson threshold
    and ``settings.min_counts``.
    """
    j, cnt, mu, keep, n_windows = window_scores(counts, background, width, support, settings)
    if support_pixels is not None:
        thr_frame = frame_threshold(n_windows, mu, support_pixels[1])
        lr = None if len(support_pixels) < 3 else support_pixels[2](j)
        keep = supported(keep, cnt, thr_frame, lr, support_pixels[0])
    return j, cnt, mu, keep


def window_scores(counts, background, width: int, support, settings: Settings):
    """The per-row part of :func:`strongest_window`: ``(j, count, mu, keep, n_windows)``,
    each (P,), ``keep`` before the neighbour support (each row's values are its own)."""
    S_w = np.rint(moving_sum(counts, width))  # window sums (integers)
    B_w = moving_sum(background, width)
    j = np.argmax(S_w - B_w, axis=1)
    rows = np.arange(counts.shape[0])
    cnt, mu = S_w[rows, j], B_w[rows, j]
    n_windows = np.maximum(1.0, np.count_nonzero(support, axis=1) / width)
    thr = poisson_isf(settings.false_alarm / n_windows, np.maximum(mu, 1e-12))
    keep = (cnt > thr) & (cnt >= settings.min_counts)
    return j, cnt, mu, keep, n_windows


#: false peaks per frame (one recording, the whole sensor) allowed among the peaks that
#: no neighbour on the same surface supports (:func:`supported`): at the per-pixel
#: level (10⁻³ nominal, 2.5·10⁻³ measured with the sliding window's clumping) a
#: 192-pixel sensor gets a false peak in about every second frame, and next to a
#: sparse surface (a few peaks) that one false point is 1–50 % of the cloud.  (10⁻³
#: cost the bundled room recording, nominal system, a correct isolated point of 3
#: detections at a scan p-value of 1.6·10⁻⁵.)
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


def excess_band(counts, background, width: int, j, level: float = 0.5):
    """Per row, the contiguous steps around ``j`` where the moving excess stays
    at or above ``level`` times its value at ``j``.

    ``counts``, ``background`` : (Q, S); ``j`` : (Q,) int.  Returns ``(lo, hi)``,
    each (Q,) int64 (inclusive).
    """
    E = (moving_average(np.asarray(counts, np.float64), width)
         - moving_average(np.asarray(background, np.float64), width))
    Q, S = E.shape
    if Q == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.asarray(j, np.int64)
    below = E < level * E[np.arange(Q), j][:, None]
    idx = np.arange(S)[None, :]
    lo = np.where(below & (idx < j[:, None]), idx, -1).max(axis=1) + 1
    hi = np.where(below & (idx > j[:, None]), idx, S).min(axis=1) - 1
    return lo.astype(np.int64), hi.astype(np.int64)


def footprint_steps(system: System, table) -> int:
    """Angle steps over which the beam crosses one pixel (odd, >= 3).

    Numerically, at the working distance where the transmitter axis meets
    the optical axis (or 2.5 m when they do not meet): the beam's image moves
    by |d column / d θ| pixels per radian of mirror angle.
    """
    from mems_stereo.model.acquisition import shot_pixels

    sc = system.scanner
    d = 1e-4
    cols = shot_pixels(system, np.array([sc.theta0 - d, sc.theta0 + d]), 2.5)
    px_per_rad = abs(cols[1] - cols[0]) / (2 * d) if np.all(np.isfinite(cols)) else np.nan
    if not np.isfinite(px_per_rad) or px_per_rad <= 0:
        return 3
    n = int(round(1.0 / px_per_rad / table.step))
    return max(3, n + 1 - n % 2)


@dataclass
class Peaks:
    """The peaks of a recording, one per pixel at most (Q peaks).

    row, col : (Q,) int64 pixel; code : (Q,) int64, strongest code of the
    pixel's signal histogram; code_lo, code_hi : (Q,) int64, the code window
    counted in pass 2; step_lo, step_hi : (Q,) int64, the scan-angle steps
    of the interval table counted in pass 2; counts : (Q,) int64, signal
    detections in the peak's angle band; background : (Q,) float64, their
    expected background; rate_hz : (Q,) float64, the pixel's ML background
    rate; background_by_step : (Q, S) ``scipy.sparse.csr_array`` float64,
    the expected background detections per angle step over each peak's
    counted steps ``step_lo..step_hi`` (zero elsewhere; :func:`window_rows`;
    None once used up).

    ``peaks["row"]`` and ``peaks.get("row")`` read a field (mapping-style
    callers of version 0.1).
    """

    row: np.ndarray
    col: np.ndarray
    code: np.ndarray
    code_lo: np.ndarray
    code_hi: np.ndarray
    step_lo: np.ndarray
    step_hi: np.ndarray
    counts: np.ndarray
    background: np.ndarray
    rate_hz: np.ndarray
    background_by_step: object | None = None

    def __len__(self) -> int:
        return int(self.row.size)

    def pixel(self, width: int) -> np.ndarray:
        """(Q,) int64 flat pixel index ``row·width + col``."""
        return self.row * int(width) + self.col

    def __getitem__(self, name: str):
        if name not in self.__dataclass_fields__:
            raise KeyError(name)
        return getattr(self, name)

    def __contains__(self, name: str) -> bool:
        return name in self.__dataclass_fields__ and getattr(self, name) is not None

    def get(self, name: str, default=None):
        return getattr(self, name) if name in self.__dataclass_fields__ else default

    def keys(self):
        return [k for k in self.__dataclass_fields__ if getattr(self, k) is not None]

    def items(self):
        return [(k, getattr(self, k)) for k in self.keys()]

    @classmethod
    def coerce(cls, peaks) -> Peaks:
        """A :class:`Peaks` from itself or a mapping of its fields (e.g. a light copy
        sent to workers without ``background_by_step``)."""
        if isinstance(peaks, cls):
            return peaks
        return cls(**{k: peaks.get(k) for k in cls.__dataclass_fields__})

    def pop(self, name: str, default=None):
        """Drop an optional field (``background_by_step``); returns its value."""
        value = self.get(name, default)
        if name == "background_by_step":
            self.background_by_step = None
        return value


def find_peaks(system: System, signal, noise, theta, valid, settings: Settings,
               signal_angle=None, table=None, n_per_step=None) -> tuple[Peaks, np.ndarray]:
    """One peak per pixel where its signal detections cluster in scan angle.

    A pixel sees the laser spot only while the beam sweeps across the surface
    it images: true returns pile up in a band of scan angles about one pixel
    footprint wide, while background that passed the classifier spreads over
    every angle whose accepted code interval it hit.  Per pixel, the signal
    detections per angle step (``signal_angle``, from pass 1) are filtered by
    a moving sum over one footprint and compared with the exactly known
    expected background per step (:func:`expected_background_by_angle`, from
    the ML background rate of the noise histogram); the strongest excess above
    the Poisson threshold at ``settings.false_alarm`` is the peak; pixels
    whose footprint the sweep does not cross whole (the scan's turning point
    lies inside it) are left out, their stereo mean would be biased.  Much more
    sensitive than the code histogram under strong background (the
    background spreads over thousands of steps but only tens of codes).

    Returns :class:`Peaks` and the (H, W) float64 ML background rate per
    pixel, Hz.  (The paper's detector on the codes alone,
    ``find_code_peaks``, is kept as a test oracle in tests/oracles.py.)
    ``table`` : the run's interval table (default: a new one); ``n_per_step``
    : (S,) valid shots per angle step (default: counted from ``theta``,
    ``valid``).
    """
    if signal_angle is None:
        raise ValueError("signal_angle: expected the (H*W, S) signal detections per pixel and "
                         "angle step of pass 1, found None")
    H, W, n_bins = signal.shape
    P = H * W
    if table is None:
        table = interval_table(system, settings.confidence, min_range=settings.min_range)
    if n_per_step is None:
        n_per_step = table.shots_per_step(theta, valid)
    sc = peak_scores(system, np.asarray(signal).reshape(P, n_bins),
                     np.asarray(noise).reshape(P, n_bins),
                     np.asarray(signal_angle).reshape(P, table.n_steps), n_per_step, table,
                     settings, np.arange(P))
    keep = supported(sc.keep, sc.cnt, sc.thr_frame, sc.log_range, W)
    return peaks_of_scores(system, sc, keep, n_per_step, table, settings), sc.rate.reshape(H, W)


@dataclass
class PeakScores:
    """The first, per-pixel stage of :func:`find_peaks` for a block of pixels (Pb).

    pixels : (Pb,) int64 flat pixels ``row·width + col``; signal : (Pb, n_bins) the
    signal histogram; angle : (Pb, S) float64 signal detections per angle step;
    background : (Pb, S) float64 their expected background; rate : (Pb,) Hz, the ML
    background rate; j, cnt, mu, keep, n_windows : the strongest window
    (:func:`window_scores`; ``keep`` before the neighbour support); thr_frame : the
    per-frame threshold (:func:`frame_threshold`); log_range : (Pb, 3) log stereo
    range at ``j``, its resolution and slope allowance (:func:`support_ranges`).
    Every value of a pixel is its own, so blocks of pixels give the whole's values
    (the Dask runner scores blocks on its workers; :func:`supported` then needs
    ``keep, cnt, thr_frame, log_range`` of all).
    """

    pixels: np.ndarray
    signal: np.ndarray
    angle: np.ndarray
    background: np.ndarray
    rate: np.ndarray
    j: np.ndarray
    cnt: np.ndarray
    mu: np.ndarray
    keep: np.ndarray
    n_windows: np.ndarray
    thr_frame: np.ndarray
    log_range: np.ndarray

    def support_inputs(self):
        """``(keep, cnt, thr_frame, log_range)``: what :func:`supported` needs (small)."""
        return self.keep, self.cnt, self.thr_frame, self.log_range


def peak_scores(system: System, signal, noise, signal_angle, n_per_step, table,
                settings: Settings, pixels) -> PeakScores:
    """:class:`PeakScores` of the flat ``pixels`` (Pb,) from their rows ``signal``,
    ``noise`` (Pb, n_bins) int and ``signal_angle`` (Pb, S) of pass 1; ``n_per_step``
    (S,) valid shots per step; ``table`` the run's interval table."""
    pixels = np.asarray(pixels, np.int64)
    P_all = system.receiver.width * system.receiver.height
    bw = system.tdc.bin_width
    S = np.asarray(signal)
    N = np.asarray(noise)
    n_valid = int(n_per_step.sum())
    A = acceptance_counts(system, None, None, settings.confidence, settings.min_range,
                          table=table, n_per_step=n_per_step, pixels=pixels)
    rate = background_rate_from_noise(N, S + N, A, n_valid, bw)
    width = footprint_steps(system, table)
    B = expected_background_by_angle(table, n_per_step, rate, pixels)
    Hs = np.asarray(signal_angle, dtype=np.float64)
    j, cnt, mu, keep, n_windows = window_scores(Hs, B, width, B > 0, settings)
    return PeakScores(pixels, S, Hs, B, rate, j, cnt, mu, keep, n_windows,
                      frame_threshold(n_windows, mu, P_all),
                      support_ranges(system, table, pixels, j, width))


def peaks_of_scores(system: System, sc: PeakScores, keep, n_per_step, table,
                    settings: Settings) -> Peaks:
    """The :class:`Peaks` of a block of pixels (their ``candidates`` for the matched
    filter attached) from its :class:`PeakScores` and ``keep`` (Pb,) bool, its pixels'
    peaks after :func:`supported`; blocks joined with :func:`concat_peaks` are the
    whole's."""
    W = system.receiver.width
    n_bins = system.tdc.n_bins
    bw = system.tdc.bin_width
    width = footprint_steps(system, table)
    S, Hs, B, rate = sc.signal, sc.angle, sc.background, sc.rate
    j, cnt, mu, n_windows = sc.j, sc.cnt, sc.mu, sc.n_windows
    keep = np.array(keep, bool)
    keep_first = keep.copy()
    keep &= np.isfinite(rate)
    # a pixel whose footprint the sweep does not cross whole (the scan turns
    # inside it) sees only part of its surface: its stereo mean is biased
    scanned = np.flatnonzero(n_per_step)
    if scanned.size:
        keep &= (j - width // 2 >= scanned[0]) & (j + width // 2 <= scanned[-1])
    q = np.flatnonzero(keep)
    half = width + width // 2  # the footprint, the spot's blur and the peak's own spread
    # the band: where the excess stays above half its peak (a strong return fires
    # the pixel while the spot's tails are still on it: a plateau much wider than
    # the footprint, whose first maximum j need not be its centre), plus ``half``
    b_lo, b_hi = excess_band(Hs[q], B[q], width, j[q])
    if scanned.size:
        # the same for the band itself (the half maximum of the footprint-smoothed
        # excess: the returns' own extent for a full crossing, half a footprint
        # beyond a narrow cluster), with a quarter footprint of slack: a return seen
        # only where the scan turns, its shots bunched there, lies at the footprint's
        # edge, not its centre
        inside = (b_lo >= scanned[0] - width // 4) & (b_hi <= scanned[-1] + width // 4)
        q, b_lo, b_hi = q[inside], b_lo[inside], b_hi[inside]
    # the peak code: the strongest code of the signal histogram in the band's codes
    S_codes = moving_average(S[q], max(1, int(round(system.laser.pulse_fwhm / bw))) | 1)
    code = np.argmax(S_codes, axis=1) + 1 if q.size else np.zeros(0, np.int64)
    step_lo = np.maximum(0, b_lo - half).astype(np.int64)
    step_hi = np.minimum(table.n_steps - 1, b_hi + half).astype(np.int64)
    # near misses of this stage, for the matched filter over angle × code
    # (:mod:`mems_stereo.pipeline.matched`): counted over j ± (width + width // 2) (box
    # centres within a footprint of j), their background rows over j ± (width + half)
    # (the band a confirmed peak counts)
    from scipy.special import pdtrc

    ok = np.isfinite(rate.reshape(-1)) & (cnt >= settings.min_counts)
    if scanned.size:
        ok &= (j - width // 2 >= scanned[0]) & (j + width // 2 <= scanned[-1])
    with np.errstate(invalid="ignore"):
        p_adj = pdtrc(np.maximum(cnt - 1, 0), np.maximum(mu, 1e-12)) * n_windows
    # candidates: every pixel without a first-stage peak; the near misses of that stage
    # (p_adj < CANDIDATE_P) are searched around its strongest window first
    # (``local_lo``/``local_hi``), every candidate over its whole scan (below)
    qc = np.flatnonzero(~keep_first & ok).astype(np.int64)
    near = np.isin(qc, candidate_rows(p_adj, keep_first, ok))
    local_lo = np.where(near, np.maximum(0, j[qc] - width - width // 2), -1).astype(np.int64)
    local_hi = np.where(near, np.minimum(table.n_steps - 1, j[qc] + width + width // 2),
                        -1).astype(np.int64)
    if CANDIDATE_WHOLE_SCAN:
        # every step at which the pixel accepts a code (the first stage's strongest
        # window, which sums every accepted code, is where the background happened to
        # bunch when the accepted interval is much wider than the pulse: sweep case
        # 30003, 7.8 m at 13 MHz with a 6 cm baseline, the return 1,000–8,000 steps
        # from it at 78 of 80 near misses, and 76 lit pixels no near miss at all)
        has = B[qc] > 0
        some = has.any(axis=1)  # (a pixel without an accepted code has nothing to count)
        qc, near, local_lo, local_hi, has = (x[some] for x in (qc, near, local_lo,
                                                                 local_hi, has))
        c_lo = np.argmax(has, axis=1).astype(np.int64)
        c_hi = (B.shape[1] - 1 - np.argmax(has[:, ::-1], axis=1)).astype(np.int64)
        c_lo = np.where(near, np.minimum(c_lo, local_lo), c_lo)
        c_hi = np.where(near, np.maximum(c_hi, local_hi), c_hi)
    else:
        qc, local_lo, local_hi = qc[near], local_lo[near], local_hi[near]
        c_lo, c_hi = local_lo, local_hi
    b_lo = np.maximum(0, c_lo - half).astype(np.int64)
    b_hi = np.minimum(table.n_steps - 1, c_hi + half).astype(np.int64)
    pc, pq = sc.pixels[qc], sc.pixels[q]
    candidates = Peaks(
        row=(pc // W).astype(np.int64), col=(pc % W).astype(np.int64),
        code=np.zeros(qc.size, np.int64), code_lo=np.ones(qc.size, np.int64),
        code_hi=np.full(qc.size, n_bins, np.int64), step_lo=c_lo, step_hi=c_hi,
        counts=np.rint(cnt[qc]).astype(np.int64), background=mu[qc],
        rate_hz=rate.reshape(-1)[qc], background_by_step=window_rows(B, qc, b_lo, b_hi))
    candidates.n_windows = n_windows[qc]
    candidates.local_lo, candidates.local_hi = local_lo, local_hi
    candidates.width = width
    peaks = Peaks(
        row=(pq // W).astype(np.int64), col=(pq % W).astype(np.int64),
        code=code.astype(np.int64),
        code_lo=np.ones(q.size, np.int64), code_hi=np.full(q.size, n_bins, np.int64),
        step_lo=step_lo, step_hi=step_hi,
        counts=np.rint(cnt[q]).astype(np.int64), background=mu[q],
        rate_hz=rate.reshape(-1)[q], background_by_step=window_rows(B, q, step_lo, step_hi))
    peaks.candidates = candidates
    return peaks


def concat_peaks(parts) -> Peaks:
    """The :class:`Peaks` of consecutive blocks of pixels (:func:`peaks_of_scores`), in
    order, as one (their candidates joined too): the whole's, field for field."""
    from scipy.sparse import csr_array

    def join(ps):
        out = {}
        for k in Peaks.__dataclass_fields__:
            if k != "background_by_step":
                out[k] = np.concatenate([getattr(p, k) for p in ps])
        mats = [p.background_by_step for p in ps]
        off = np.cumsum([0] + [m.nnz for m in mats[:-1]])
        indptr = np.concatenate([[0]] + [m.indptr[1:] + o for m, o in zip(mats, off)])
        out["background_by_step"] = csr_array(
            (np.concatenate([m.data for m in mats]), np.concatenate([m.indices for m in mats]),
             indptr.astype(mats[0].indptr.dtype)), shape=(int(indptr.size - 1),
                                                          mats[0].shape[1]))
        return Peaks(**out)

    parts = list(parts)
    peaks = join(parts)
    cands = join([p.candidates for p in parts])
    cands.n_windows = np.concatenate([p.candidates.n_windows for p in parts])
    cands.local_lo = np.concatenate([p.candidates.local_lo for p in parts])
    cands.local_hi = np.concatenate([p.candidates.local_hi for p in parts])
    cands.width = parts[0].candidates.width
    peaks.candidates = cands
    return peaks


#: near misses of the first stage: pixels whose strongest window's p-value, times the
#: number of window positions, is below this; the matched filter searches the
#: footprints around that window first (at the level of that window's code boxes)
CANDIDATE_P = 0.5
#: whether the matched filter also searches the whole scan of every pixel without a
#: first-stage peak (True; at the level of the scan's accepted area), or only the near
#: misses' windows (see :func:`peaks_of_scores`; sweep case 30003: coverage 0.11 →
#: 0.48, the oracle with the widest interval's look-elsewhere level 0.38)
CANDIDATE_WHOLE_SCAN = True


def candidate_rows(p_adjusted, keep, ok) -> np.ndarray:
    """(C,) int64 rows (pixels) that missed the first stage by little:
    ``p_adjusted`` (P,) the strongest window's Poisson p-value times its number of
    window positions, ``keep`` (P,) bool the first stage's peaks, ``ok`` (P,) bool
    pixels that may hold a peak at all (known rate, footprint inside the scan)."""
    return np.flatnonzero(~keep & ok & (p_adjusted < CANDIDATE_P)).astype(np.int64)


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


def window_rows(B, q, lo, hi):
    """(Q, S) ``scipy.sparse.csr_array`` of rows ``q`` (Q,) of ``B`` (P, S) over the
    columns ``lo[i]..hi[i]`` of each row (zero outside), without a dense (Q, S) copy."""
    from scipy.sparse import csr_array

    q, lo, hi = (np.asarray(x, np.int64).ravel() for x in (q, lo, hi))
    n = np.maximum(hi - lo + 1, 0)
    indptr = np.zeros(q.size + 1, np.int64)
    np.cumsum(n, out=indptr[1:])
    row = np.repeat(np.arange(q.size), n)
    col = np.arange(indptr[-1]) - indptr[:-1][row] + lo[row]
    return csr_array((np.asarray(B)[q[row], col], col, indptr), shape=(q.size, B.shape[1]))
