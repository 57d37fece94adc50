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

from mems_stereo.model.system import System
from mems_stereo.physics.background import (
    background_rate_at_steps,
    background_rate_from_noise,
    moving_sum,
    poisson_isf,
)
from mems_stereo.physics.pulse import effective_fwhm
from mems_stereo.pipeline.acceptance import acceptance_counts
from mems_stereo.pipeline.histograms import moving_average, moving_average_argmax
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.peak_support import (
    SupportInputs,
    frame_threshold,
    support_ranges,
    supported,
)
from mems_stereo.pipeline.peak_table import Candidates, Peaks
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.step_windows import (
    WindowMax,
    background_at_steps,
    dense_rows,
    step_span,
    strongest_windows,
    visited_excess_band,
    visited_window_rows,
)


@dataclass(frozen=True, slots=True)
class WindowScores:
    """Per row (pixel) the window of ``width`` angle steps with the largest excess over
    the background (:func:`window_scores`, :func:`strongest_window`), each (P,).

    j : int64, the window's centre index; cnt : float64, its count (an integer);
    mu : float64, its expected background; keep : bool, whether it passes the Poisson
    threshold and ``settings.min_counts`` (and, from :func:`strongest_window` with
    ``support_pixels``, the neighbour support); n_windows : float64, the row's
    independent window positions (its support over ``width``, at least 1).
    """

    j: np.ndarray
    cnt: np.ndarray
    mu: np.ndarray
    keep: np.ndarray
    n_windows: np.ndarray


def strongest_window(counts, background, width: int, support, settings: Settings,
                     support_pixels: tuple | None = None) -> WindowScores:
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
    (:func:`~mems_stereo.pipeline.peak_support.neighbour_support`: none within
    :data:`~mems_stereo.pipeline.peak_support.SUPPORT_COLUMNS` at an agreeing range) must also
    pass the sensor's per-frame threshold
    (:func:`~mems_stereo.pipeline.peak_support.frame_threshold`:
    :data:`~mems_stereo.pipeline.peak_support.FRAME_FALSE_ALARMS` false peaks per recording,
    scan statistics of the sliding window): a dense surface images onto neighbouring pixels,
    while a background false alarm is isolated or sits next to
    a sparse surface, whose few peaks would lend it their support.
    Returns :class:`WindowScores` (``keep`` with the neighbour support when
    ``support_pixels`` is given).
    """
    ws = window_scores(counts, background, width, support, settings)
    if support_pixels is None:
        return ws
    thr_frame = frame_threshold(ws.n_windows, ws.mu, support_pixels[1])
    lr = None if len(support_pixels) < 3 else support_pixels[2](ws.j)
    return WindowScores(ws.j, ws.cnt, ws.mu,
                        supported(ws.keep, ws.cnt, thr_frame, lr, support_pixels[0]),
                        ws.n_windows)


def window_scores(counts, background, width: int, support, settings: Settings) -> WindowScores:
    """The per-row part of :func:`strongest_window`: :class:`WindowScores` with ``keep``
    before the neighbour support (each row's values are its own)."""
    S_w = np.rint(moving_sum(counts, width))  # window sums (integers)
    B_w = moving_sum(background, width)
    j = np.argmax(S_w - B_w, axis=1)
    rows = np.arange(counts.shape[0])
    return window_scores_of(WindowMax(j, S_w[rows, j], B_w[rows, j],
                                      np.count_nonzero(support, axis=1)), width, settings)


def window_scores_of(wm: WindowMax, width: int, settings: Settings) -> WindowScores:
    """:class:`WindowScores` of the strongest windows ``wm`` (``n_positive``: each row's
    steps where background can occur)."""
    n_windows = np.maximum(1.0, wm.n_positive / width)
    thr = poisson_isf(settings.false_alarm / n_windows, np.maximum(wm.mu, 1e-12))
    keep = (wm.cnt > thr) & (wm.cnt >= settings.min_counts)
    return WindowScores(wm.j, wm.cnt, wm.mu, keep, n_windows)


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
    by |d column / d θ| pixels per radian of mirror angle.  Kept per (system,
    table step) for the next frames (systems are frozen).
    """
    key = (id(system), float(table.step))
    hit = _FOOTPRINTS.get(key)
    if hit is not None and hit[0] is system:
        return hit[1]
    from mems_stereo.model.acquisition import shot_pixels

    sc = system.scanner
    d = 1e-4
    cols = shot_pixels(system, np.array([sc.theta0 - d, sc.theta0 + d]), 2.5)
    px_per_rad = abs(cols[1] - cols[0]) / (2 * d) if np.all(np.isfinite(cols)) else np.nan
    width = 3
    if np.isfinite(px_per_rad) and px_per_rad > 0:
        n = int(round(1.0 / px_per_rad / table.step))
        width = max(3, n + 1 - n % 2)
    if len(_FOOTPRINTS) >= 8:
        _FOOTPRINTS.clear()
    _FOOTPRINTS[key] = (system, width)
    return width


#: :func:`footprint_steps` by (id of the system, table step): (system, steps)
_FOOTPRINTS: dict = {}


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
    lies inside it) are marked ``turning``: their stereo mean is biased and carries a
    systematic σ (:func:`~mems_stereo.pipeline.peak_estimates.peak_means_of`).  Much more
    sensitive than the code histogram under strong background (the
    background spreads over thousands of steps but only tens of codes).

    Returns :class:`~mems_stereo.pipeline.peak_table.Peaks` (with their
    :class:`~mems_stereo.pipeline.peak_table.Candidates`) and the (H, W) float64 ML
    background rate per pixel, Hz.  (The paper's detector on the codes alone,
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



@dataclass(frozen=True, slots=True)
class PeakScores:
    """The first, per-pixel stage of :func:`find_peaks` for a block of pixels (Pb).

    pixels : (Pb,) int64 flat pixels ``row·width + col``; signal : (Pb, n_bins) the
    signal histogram; steps : (U,) int64 the angle steps with valid shots (increasing;
    every other step has no detection and no background); angle : (Pb, U) float64
    signal detections at those steps; background : (Pb, U) float64 their expected
    background; rate : (Pb,) Hz, the ML background rate; j, cnt, mu, keep, n_windows :
    the strongest window (:func:`window_scores`; ``keep`` before the neighbour
    support); thr_frame : the per-frame threshold
    (:func:`~mems_stereo.pipeline.peak_support.frame_threshold`); log_range : (Pb, 3) log stereo
    range at ``j``, its resolution and slope allowance
    (:func:`~mems_stereo.pipeline.peak_support.support_ranges`) — these two of the pixels
    with ``keep`` alone (inf, NaN elsewhere: the support reads no other). Every value of a
    pixel is its own, so blocks of pixels give the whole's values (the Dask runner scores
    blocks on its workers; :func:`~mems_stereo.pipeline.peak_support.supported` then needs
    the :meth:`support_inputs` of all).
    """

    pixels: np.ndarray
    signal: np.ndarray
    steps: np.ndarray
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


    def support_inputs(self) -> SupportInputs:
        """What :func:`~mems_stereo.pipeline.peak_support.supported` needs of these pixels
        (small), and their rate."""
        return SupportInputs(self.keep, self.cnt, self.thr_frame, self.log_range, self.rate)


def peak_scores(system: System, signal, noise, signal_angle, n_per_step, table,
                settings: Settings, pixels) -> PeakScores:
    """:class:`PeakScores` of the flat ``pixels`` (Pb,) from their rows ``signal``,
    ``noise`` (Pb, n_bins) int and ``signal_angle`` (Pb, S) of pass 1; ``n_per_step``
    (S,) valid shots per step; ``table`` the run's interval table.  Its cost follows
    the steps with valid shots (:mod:`~mems_stereo.pipeline.step_windows`), not all S."""
    pixels = np.asarray(pixels, np.int64)
    P_all = system.receiver.width * system.receiver.height
    bw = system.tdc.bin_width
    S = np.asarray(signal)
    N = np.asarray(noise)
    n_per_step = np.asarray(n_per_step)
    used = np.flatnonzero(n_per_step)
    table.ensure(used)
    at = _table_index(used, pixels)
    lo, hi = table.lo[at], table.hi[at]  # (U, Pb) the accepted codes at the visited steps
    rate = background_rate_at_steps(N, S, lo, hi, n_per_step[used], int(n_per_step.sum()), bw)
    if rate is None:
        A = acceptance_counts(system, None, None, settings.confidence, settings.min_range,
                              table=table, n_per_step=n_per_step, pixels=pixels)
        rate = background_rate_from_noise(N, S + N, A, int(n_per_step.sum()), bw)
    width = footprint_steps(system, table)
    B = background_at_steps(lo, hi, n_per_step[used], rate, bw)
    Hs = np.asarray(signal_angle)[:, used].astype(np.float64)
    wm = strongest_windows(Hs, B, used, table.n_steps, width)
    ws = window_scores_of(wm, width, settings)
    # the neighbour support reads the threshold and ranges of pixels with a peak alone
    k = np.flatnonzero(ws.keep)
    thr_frame = np.full(pixels.size, np.inf)
    thr_frame[k] = frame_threshold(ws.n_windows[k], ws.mu[k], P_all)
    log_range = np.full((pixels.size, 3), np.nan)
    log_range[k] = support_ranges(system, table, pixels[k], ws.j[k], width)
    return PeakScores(pixels, S, used, Hs, B, rate, ws.j, ws.cnt, ws.mu, ws.keep,
                      ws.n_windows, thr_frame, log_range)


def _table_index(steps, pixels):
    """The index of the interval table's (U, Pb) rows ``steps``, columns ``pixels``:
    ``np.ix_``, or a row gather and a slice where the pixels are consecutive (a block,
    or all; faster than a gather of single elements)."""
    if pixels.size and pixels[-1] - pixels[0] == pixels.size - 1 and bool(
            np.all(np.diff(pixels) == 1)):
        return steps, slice(int(pixels[0]), int(pixels[-1]) + 1)
    return np.ix_(steps, pixels)


def peaks_of_scores(system: System, sc: PeakScores, keep, n_per_step, table,
                    settings: Settings) -> Peaks:
    """The :class:`~mems_stereo.pipeline.peak_table.Peaks` of a block of pixels (with
    their :class:`~mems_stereo.pipeline.peak_table.Candidates` for the matched filter)
    from its :class:`PeakScores` and ``keep`` (Pb,) bool, its pixels' peaks after
    :func:`~mems_stereo.pipeline.peak_support.supported`; blocks joined with
    :func:`concat_peaks` are the whole's."""
    width = footprint_steps(system, table)
    keep_first = np.array(keep, bool)
    scanned = np.flatnonzero(n_per_step)
    peaks = _first_stage_peaks(system, sc, keep_first, scanned, width, table)
    return Peaks(**peaks.arrays(), background_by_step=peaks.background_by_step,
                 candidates=_candidates(system, sc, keep_first, scanned, width, table,
                                        settings))


def _first_stage_peaks(system: System, sc: PeakScores, keep_first, scanned, width: int,
                       table) -> Peaks:
    """The peaks of :func:`peaks_of_scores`: the supported pixels ``keep_first`` with a
    known rate, ``turning`` where their footprint or band does not lie inside the
    ``scanned`` steps."""
    W = system.receiver.width
    n_bins = system.tdc.n_bins
    bw = system.tdc.bin_width
    S, rate = sc.signal, sc.rate
    j, cnt, mu = sc.j, sc.cnt, sc.mu
    n_steps = table.n_steps
    keep = keep_first & np.isfinite(rate)
    # a pixel whose footprint the sweep does not cross whole (the scan turns
    # inside it) sees only part of its surface: its stereo mean is biased, its
    # time of flight is not (each return lies on its own shot's ray): kept, marked
    cut = np.zeros(j.shape, bool)
    if scanned.size:
        cut = (j - width // 2 < scanned[0]) | (j + width // 2 > scanned[-1])
    q = np.flatnonzero(keep)
    half = width + width // 2  # the footprint, the spot's blur and the peak's own spread
    # the band: where the excess stays above half its peak (a strong return fires
    # the pixel while the spot's tails are still on it: a plateau much wider than
    # the footprint, whose first maximum j need not be its centre), plus ``half``
    band = visited_excess_band(sc.angle, sc.background, sc.steps, n_steps, width, q, j[q])
    if band is None:  # (the NumPy form: the rows laid out over all steps)
        band = excess_band(dense_rows(sc.angle, sc.steps, n_steps, q),
                           dense_rows(sc.background, sc.steps, n_steps, q), width, j[q])
    b_lo, b_hi = band
    if scanned.size:
        # the same for the band itself (the half maximum of the footprint-smoothed
        # excess: the returns' own extent for a full crossing, half a footprint
        # beyond a narrow cluster), with a quarter footprint of slack: a return seen
        # only where the scan turns, its shots bunched there, lies at the footprint's
        # edge, not its centre
        inside = (b_lo >= scanned[0] - width // 4) & (b_hi <= scanned[-1] + width // 4)
        cut[q[~inside]] = True
    # the peak code: the strongest code of the signal histogram in the band's codes
    fwhm_bins = max(1, int(round(effective_fwhm(system.laser) / bw))) | 1
    code = (moving_average_argmax(S[q], fwhm_bins) + 1 if q.size
            else np.zeros(0, np.int64))
    step_lo = np.maximum(0, b_lo - half).astype(np.int64)
    step_hi = np.minimum(table.n_steps - 1, b_hi + half).astype(np.int64)
    pq = sc.pixels[q]
    return Peaks(
        row=(pq // W).astype(np.int64), col=(pq % W).astype(np.int64),
        code=code.astype(np.int64),
        code_lo=np.ones(q.size, np.int64), code_hi=np.full(q.size, n_bins, np.int64),
        step_lo=step_lo, step_hi=step_hi,
        counts=np.rint(cnt[q]).astype(np.int64), background=mu[q],
        rate_hz=rate.reshape(-1)[q], turning=cut[q],
        background_by_step=visited_window_rows(sc.background, sc.steps, n_steps, q, step_lo,
                                               step_hi))


def _candidates(system: System, sc: PeakScores, keep_first, scanned, width: int, table,
                settings: Settings) -> Candidates:
    """The candidates of :func:`peaks_of_scores`: every pixel without a first-stage peak
    that may hold one; the near misses of that stage (``p_adj`` below
    :data:`CANDIDATE_P`) are searched around its strongest window first
    (``local_lo``/``local_hi``), every candidate over its whole scan."""
    from scipy.special import pdtrc

    W = system.receiver.width
    n_bins = system.tdc.n_bins
    rate = sc.rate
    j, cnt, mu, n_windows = sc.j, sc.cnt, sc.mu, sc.n_windows
    half = width + width // 2  # the footprint, the spot's blur and the peak's own spread
    ok = np.isfinite(rate.reshape(-1)) & (cnt >= settings.min_counts)
    if scanned.size:
        ok &= (j - width // 2 >= scanned[0]) & (j + width // 2 <= scanned[-1])
    with np.errstate(invalid="ignore"):
        p_adj = pdtrc(np.maximum(cnt - 1, 0), np.maximum(mu, 1e-12)) * n_windows
    qc = np.flatnonzero(~keep_first & ok).astype(np.int64)
    near = np.isin(qc, candidate_rows(p_adj, keep_first, ok))
    local_lo = np.where(near, np.maximum(0, j[qc] - width - width // 2), -1).astype(np.int64)
    local_hi = np.where(near, np.minimum(table.n_steps - 1, j[qc] + width + width // 2),
                        -1).astype(np.int64)
    if CANDIDATE_WHOLE_SCAN:
        # every step at which the pixel accepts a code (the first stage's strongest
        # window, which sums every accepted code, is where the background happened to
        # bunch when the accepted interval is much wider than the pulse: the return can
        # lie thousands of steps from it, or the pixel be no near miss at all)
        some, c_lo, c_hi = step_span(sc.background[qc], sc.steps)
        # (a pixel without an accepted code has nothing to count)
        qc, near, local_lo, local_hi, c_lo, c_hi = (x[some] for x in (qc, near, local_lo,
                                                                      local_hi, c_lo, c_hi))
        c_lo = np.where(near, np.minimum(c_lo, local_lo), c_lo)
        c_hi = np.where(near, np.maximum(c_hi, local_hi), c_hi)
    else:
        qc, local_lo, local_hi = qc[near], local_lo[near], local_hi[near]
        c_lo, c_hi = local_lo, local_hi
    b_lo = np.maximum(0, c_lo - half).astype(np.int64)
    b_hi = np.minimum(table.n_steps - 1, c_hi + half).astype(np.int64)
    pc = sc.pixels[qc]
    return Candidates(
        row=(pc // W).astype(np.int64), col=(pc % W).astype(np.int64),
        code=np.zeros(qc.size, np.int64), code_lo=np.ones(qc.size, np.int64),
        code_hi=np.full(qc.size, n_bins, np.int64), step_lo=c_lo, step_hi=c_hi,
        counts=np.rint(cnt[qc]).astype(np.int64), background=mu[qc],
        rate_hz=rate.reshape(-1)[qc],
        background_by_step=visited_window_rows(sc.background, sc.steps, table.n_steps, qc,
                                               b_lo, b_hi),
        n_windows=n_windows[qc], local_lo=local_lo, local_hi=local_hi, width=width)


def concat_peaks(parts) -> Peaks:
    """The :class:`~mems_stereo.pipeline.peak_table.Peaks` of consecutive blocks of
    pixels (:func:`peaks_of_scores`), in order, as one (their candidates joined too):
    the whole's, field for field."""
    parts = list(parts)
    peaks = Peaks.concat(parts)
    return Peaks(**peaks.arrays(), background_by_step=peaks.background_by_step,
                 candidates=Candidates.concat([p.candidates for p in parts]))


#: near misses of the first stage: pixels whose strongest window's p-value, times the
#: number of window positions, is below this; the matched filter searches the
#: footprints around that window first (at the level of that window's code boxes)
CANDIDATE_P = 0.5
#: whether the matched filter also searches the whole scan of every pixel without a
#: first-stage peak (True; at the level of the scan's accepted area), or only the near
#: misses' windows (see :func:`peaks_of_scores`)
CANDIDATE_WHOLE_SCAN = True


def candidate_rows(p_adjusted, keep, ok) -> np.ndarray:
    """(C,) int64 rows (pixels) that missed the first stage by little:
    ``p_adjusted`` (P,) the strongest window's Poisson p-value times its number of
    window positions, ``keep`` (P,) bool the first stage's peaks, ``ok`` (P,) bool
    pixels that may hold a peak at all (known rate, footprint inside the scan)."""
    return np.flatnonzero(~keep & ok & (p_adjusted < CANDIDATE_P)).astype(np.int64)
