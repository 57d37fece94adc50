"""Points from detections: stereo and time-of-flight estimates, fused by their covariances.

For a detection (shot k, pixel (col, row), code N) with scan angle θ_k there
are two estimates of the same point on the scanner ray ``x = p + s·d(θ)``:

* stereo: the pixel ray meets the scanner ray (pixel + scan angle, no time):
  sharp at short range, its spread grows as range² / (f·b);
* time of flight: the point at path length L on the scanner ray (L + scan
  angle): its spread along the ray is about c·σ_t / 2 at every range
  (≈ 0.95 m with the 14.9 ns pulse).

Given θ the two are independent (the pixel versus the timing), so they are
fused along the ray by inverse-variance weights of their conditional
along-ray variances, ``s_f = w·s_st + (1 − w)·s_tof`` with
``w = var_tof / (var_st + var_tof)``; the fused point's covariance is
propagated to first order from every spread (pixel, timing, scan angle,
optional calibration covariance) through that fixed-weight combination.
A peak (the signal detections of one pixel inside a code window) averages
its detections' estimates; the errors of different shots are independent, so
its covariance is ``Σ C_i / n²``.  Units: metres, receiver camera frame.

A SPAD records a shot's first photon only, so the time of flight of a strong
return is early (first-photon pile-up) and one at the TDC start late; given
the valid shots per scan-angle step, :class:`PeakAccumulator` estimates each
peak's signal photons per shot from which shots fired and removes that delay
from the ToF (and, by its share, the fused) estimate, with its uncertainty
(:func:`first_photon_moments`, :func:`first_photon_delay`).
"""

from __future__ import annotations

import numpy as np

from mems_stereo.model.system import System
from mems_stereo.model.tdc import detection_codes
from mems_stereo.physics.spot import segment_dot, step_directions
from mems_stereo.pipeline.background_entries import (
    BackgroundEntries,
    BackgroundSubtraction,
    StepEntries,
)
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.consistency import k_from_confidence
from mems_stereo.pipeline.fusion_inputs import FusionEntries, FusionOptions, FusionPeaks
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.pass2 import PeakCounts, decode_peak_keys
from mems_stereo.pipeline.peak_accumulator import EntryPoints, PeakAccumulator
from mems_stereo.pipeline.settings import Settings

#: entries (detections, or distinct (peak, step, code) keys) evaluated at once by
#: :func:`accumulate_entries`; sums are sequential in entry order, so the blocks
#: change no bit of the result
ENTRY_BLOCK = 1 << 15


def points_from_counts(system: System, peaks, counts: PeakCounts, settings: Settings,
                       shots_per_step=None, table=None, own=None):
    """The cloud: one fused point per peak from its counted detections.

    Each distinct (peak, step, code) is triangulated once at the step's grid
    angle (the angle it was classified with) and weighted by its count, less the
    expected background of its (peak, step) where the peaks carry ``rate_hz``
    (:mod:`~mems_stereo.pipeline.background_entries`).
    Peaks whose stereo and ToF ranges disagree are left out
    (:func:`consistent_points`).
    ``peaks`` : a mapping of (Q,) arrays (:func:`accumulator_for_peaks`).
    ``shots_per_step`` : (S,) int, valid shots per angle step of the interval
    table (:func:`~mems_stereo.pipeline.intervals.shots_per_step`): with it the ToF and
    fused estimates are corrected for the first-photon delay
    (:class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator`).
    ``table`` : the run's interval table (default: a new one; only its grid is used).
    ``own`` : (a, b) or None, see :meth:`PeakAccumulator.cloud`.
    """
    acc = peak_sums_from_counts(system, peaks, counts, settings, shots_per_step, table)
    return consistent_points(acc.cloud(settings.min_counts, own), settings.confidence)


def accumulator_for_peaks(system: System, peaks, settings: Settings,
                          shots_per_step=None, table=None) -> PeakAccumulator:
    """An empty :class:`PeakAccumulator` of the peaks (a mapping of (Q,) arrays
    ``row``, ``col``, ``code``, optionally ``rate_hz``, ``step_lo``, ``step_hi``)."""
    if table is None:
        table = interval_table(system, settings.confidence, min_range=settings.min_range)
    fp = FusionPeaks(peaks.row, peaks.col, peaks.code, rate_hz=peaks.rate_hz,
                     step_window=(peaks.step_lo, peaks.step_hi)
                     if peaks.step_lo is not None else None,
                     accept=_acceptance(system, table, peaks),
                     turning=getattr(peaks, "turning", None))
    return PeakAccumulator(system, fp, FusionOptions(
        confidence=settings.confidence, shots_per_step=shots_per_step,
        step_grid=(table.theta_min, table.step)))


def peak_sums_from_counts(system: System, peaks, counts: PeakCounts, settings: Settings,
                          shots_per_step=None, table=None) -> PeakAccumulator:
    """The :class:`PeakAccumulator` of the peaks after both sub-passes over their
    counted entries (arguments as :func:`points_from_counts`, whose cloud is
    ``acc.cloud(settings.min_counts)``).  The sums of a peak are its entries'
    alone: the accumulators of blocks of peaks joined
    (:meth:`PeakAccumulator.joined`) are the whole's, bit for bit."""
    if table is None:
        table = interval_table(system, settings.confidence, min_range=settings.min_range)
    S, nb = table.n_steps, system.tdc.n_bins + 1
    q, step, code = decode_peak_keys(counts.keys, S, nb)
    counted = StepEntries(q, step, code, counts.counts, table.theta_min + step * table.step)
    if peaks.rate_hz is None or shots_per_step is None or not counts.keys.size:
        acc = accumulator_for_peaks(system, peaks, settings, shots_per_step, table)
        return accumulate_entries(acc, FusionEntries(
            np.arange(q.size), q, code.astype(np.float64), counted.theta,
            weight=counts.counts.astype(np.float64)))
    # background subtraction: each (peak, step)'s expected background enters as
    # negative-weight entries, over its code window in sub-pass 1 and over its
    # inlier codes in sub-pass 2
    sub = BackgroundSubtraction(peaks, table, shots_per_step, system.receiver.width,
                                system.tdc.bin_width)
    entries = sub.window_entries(counted)
    acc = accumulator_for_peaks(system, peaks, settings, shots_per_step, table)
    return accumulate_entries(acc, entries,
                              inlier_background=lambda a: sub.inlier_entries(a, counted))


def _acceptance(system: System, table, peaks):
    """accept(steps (Q, B), centre (Q,) m, q=None, cuts=None) -> (Q, B) bool (rows: the
    peaks ``q``, default all): whether the code of a return
    from the peak's centre range, at each step's grid angle, lies in the pixel's
    accepted interval (else the classifier labels it noise: such shots are
    neither hits nor misses of the first-photon likelihood).  ``cuts``: segments of
    the flattened entries evaluated as separate calls would
    (:func:`~mems_stereo.physics.spot.segment_dot`)."""
    W = system.receiver.width
    pix = (peaks.row * W + peaks.col).astype(np.int64)

    def accept(steps, centre, q=None, cuts=None):
        px = pix if q is None else pix[q]
        d = step_directions(system.scanner, table.theta_min, table.step, steps.ravel())
        p = np.asarray(system.scanner.position, dtype=np.float64)
        pd = segment_dot(d, p, cuts)
        r = np.broadcast_to(np.asarray(centre, np.float64)[:, None], steps.shape).ravel()
        with np.errstate(invalid="ignore"):
            s = -pd + np.sqrt(pd * pd - p @ p + r ** 2)
        pxb = np.broadcast_to(px[:, None], steps.shape).ravel()
        code = np.floor(detection_codes(s + r, system, pxb))
        code = code.reshape(steps.shape)
        table.ensure(steps.ravel())  # (sorts the steps only where rows are missing)
        lo = table.lo[steps, px[:, None]]
        hi = table.hi[steps, px[:, None]]
        return (code >= lo) & (code <= hi)

    return accept


def points_from_peak_detections(system: System, entries: FusionEntries, peaks: FusionPeaks,
                                options: FusionOptions | None = None, min_counts: int = 1,
                                own=None) -> PointCloud:
    """One fused point per peak from the signal detections inside its code window.

    In-memory form of :class:`PeakAccumulator` (same result as streaming it).

    Parameters
    ----------
    entries : the detections (:class:`~mems_stereo.pipeline.fusion_inputs.FusionEntries`:
        shot, peak, code, the shots' angles, optional weights and subtracted background).
    peaks : the Q peaks (:class:`~mems_stereo.pipeline.fusion_inputs.FusionPeaks`:
        pixels, the detector's peak code kept as the ``code`` attribute when given).
    options : :class:`~mems_stereo.pipeline.fusion_inputs.FusionOptions` (default
        all defaults): with ``shots_per_step`` and ``step_grid`` (and
        ``first_photon``) the ToF and fused estimates are corrected for the
        first-photon delay and the cloud gains ``tof_delay`` (s, the delay removed)
        and ``signal_photons`` (μ0 per shot); without them the result is the
        uncorrected one.
    min_counts : peaks with fewer inlier detections are dropped.
    own : (a, b) or None, see :meth:`PeakAccumulator.cloud`.
    """
    acc = PeakAccumulator(system, peaks, options)
    return accumulate_entries(acc, entries).cloud(min_counts, own)


def accumulate_entries(acc: PeakAccumulator, entries: FusionEntries,
                       inlier_background=None) -> PeakAccumulator:
    """Both sub-passes of ``acc`` over the entries; returns ``acc``, its centres fixed
    and its sums added.

    ``inlier_background`` (optional): ``f(acc) -> BackgroundEntries``, called after
    the centres are fixed: sub-pass 2's background entries (weight −background) in
    place of the entries with ``background > 0``, which then count only in the
    window (the first-photon likelihood)."""
    shot = np.asarray(entries.shot, dtype=np.int64).ravel()
    peak, code, theta, weight = entries.peak, entries.code, entries.theta, entries.weight
    background = entries.background
    M = shot.size
    bg = None if background is None else np.asarray(background, np.float64).ravel()
    may = None if inlier_background is None or bg is None else ~(bg > 0)
    if M <= ENTRY_BLOCK:  # the entries' points computed once, used by both sub-passes
        pts = acc.entry_points(shot, peak, code, theta, weight)
        acc.add_mode_entries(pts)
        acc.finish_mode()
        if may is None:
            acc.add_inlier_entries(pts, shot, theta, background)
        else:
            acc.add_inlier_entries(pts, shot, theta, bg, may_be_inlier=may)
            _add_inlier_background(acc, inlier_background(acc))
        acc.release_stereo_cache()  # (the sub-passes' stereo geometry: no longer needed)
        return acc
    # blocks of entries: temporaries bounded by ENTRY_BLOCK whatever M.  Sub-pass 1
    # keeps each entry's fused range, its σ and ok (17 bytes an entry), from the fused
    # points alone; sub-pass 2 computes the points of the inliers (the same bits: each
    # entry's points are its own)
    peak = np.asarray(peak, dtype=np.int64).ravel()
    code = np.asarray(code, dtype=np.float64).ravel()
    m = (np.ones(M) if weight is None else np.asarray(weight, dtype=np.float64).ravel())
    r, sr, ok = np.empty(M), np.empty(M), np.empty(M, bool)
    th = np.asarray(theta, dtype=np.float64)
    for a in range(0, M, ENTRY_BLOCK):
        e = slice(a, a + ENTRY_BLOCK)
        f = acc.fused_ranges(peak[e], code[e], th[shot[e]])
        r[e], sr[e], ok[e] = f.r, f.sigma_r, f.ok
        acc.add_mode_entries(f.with_weight(code[e], m[e]))
    acc.finish_mode()
    for a in range(0, M, ENTRY_BLOCK):
        e = slice(a, a + ENTRY_BLOCK)
        pe, ce, se = peak[e], code[e], shot[e]

        def dp_of(inl, pe=pe, ce=ce, se=se):
            return acc.points_of(se[inl], pe[inl], ce[inl], theta)

        acc.add_inlier_entries(EntryPoints(pe, ce, r[e], sr[e], ok[e], m[e]), se, theta,
                               None if bg is None else bg[e], inlier_points=dp_of,
                               may_be_inlier=None if may is None else may[e])
    if may is not None:
        _add_inlier_background(acc, inlier_background(acc))
    acc.release_stereo_cache()
    return acc


def _add_inlier_background(acc: PeakAccumulator, entries: BackgroundEntries) -> None:
    """Sub-pass 2 over background entries: weight −background, inlier sums only (not
    the window), in blocks."""
    peak, code, theta, b = entries.peak, entries.code, entries.theta, entries.background
    for a in range(0, peak.size, ENTRY_BLOCK):
        e = slice(a, a + ENTRY_BLOCK)
        sh = np.arange(peak[e].size)
        pe, ce, te = peak[e], code[e], theta[e]
        f = acc.fused_ranges(pe, ce, te)

        def dp_of(inl, pe=pe, ce=ce, te=te):  # the inliers' points alone (the same bits)
            return acc.points_of(np.arange(int(inl.sum())), pe[inl], ce[inl], te[inl])

        acc.add_inlier_entries(EntryPoints(pe, ce, f.r, f.sigma_r, f.ok, -b[e]), sh, te, b[e],
                               inlier_points=dp_of, count_window=False)


def consistent_points(cloud: PointCloud, confidence: float = 0.997) -> PointCloud:
    """The points whose stereo and time-of-flight ranges agree within the bound.

    Two estimates of one surface must agree: a peak whose ranges differ by
    more than ``k·sqrt(σ_stereo² + σ_tof²)`` (attribute ``stereo_tof_z`` > k,
    k from ``confidence``) is not one surface — a false peak of background, or
    two surfaces inside one pixel — and is left out.
    """
    if "stereo_tof_z" not in cloud.attributes:
        return cloud
    return cloud.select(~(cloud["stereo_tof_z"] > k_from_confidence(confidence)))
