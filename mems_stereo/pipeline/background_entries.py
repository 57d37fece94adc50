"""The background the fusion subtracts from a peak's counted entries, as entries of
negative weight.

Each (peak, angle step) group of pass 2's counts expects background detections
inside its counted codes (:func:`~mems_stereo.pipeline.window_background.window_background`);
sub-pass 1 subtracts them over the whole code window (:meth:`BackgroundSubtraction.
window_entries`), sub-pass 2 over the codes that pass the inlier test, at every
step of the inliers' band, with a detection or not (:meth:`BackgroundSubtraction.
inlier_entries`, :func:`with_empty_steps`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mems_stereo.pipeline.fusion_inputs import FusionEntries
from mems_stereo.pipeline.window_background import inlier_codes, window_background

#: fewest valid shots per valid angle step, on average over a peak's band, for the
#: background of its steps without a detection to be subtracted (:func:`with_empty_steps`;
#: as ``first_photon_correction.BINOMIAL_MIN_SHOTS``: a scan that revisits its angles)
DENSE_BAND_SHOTS = 2.0


@dataclass(frozen=True, slots=True, eq=False)
class StepEntries:
    """Entries of pass 2's counts, one per distinct (peak, step, code).

    peak, step : (M,) int64; code : (M,) int TDC code; weight : (M,) their counts;
    theta : (M,) float64 rad, the step's grid angle.
    """

    peak: np.ndarray
    step: np.ndarray
    code: np.ndarray
    weight: np.ndarray
    theta: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class CodeWindows:
    """The counted codes of entries (M,) of (peak, step): ``lo`` int64 the start of
    the pixel's accepted interval at the step, ``a``, ``b`` the accepted interval ∩
    the peak's code window, ``shots`` the step's valid shots."""

    lo: np.ndarray
    a: np.ndarray
    b: np.ndarray
    shots: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class BackgroundEntries:
    """Background entries (N,) each: ``peak`` int64, ``code`` float64 (a segment's
    centroid), ``theta`` float64 rad, ``background`` float64 expected detections."""

    peak: np.ndarray
    code: np.ndarray
    theta: np.ndarray
    background: np.ndarray


def is_in(a, b) -> np.ndarray:
    """``np.isin(a, b)`` (int64 arrays); by binary search where ``b`` is sorted (the
    fusion's entries are, by peak and step), without sorting both arrays."""
    b = np.asarray(b)
    if b.size == 0 or not bool(np.all(b[1:] >= b[:-1])):
        return np.isin(a, b)
    i = np.minimum(np.searchsorted(b, a), b.size - 1)
    return b[i] == a


def with_empty_steps(band, entries: StepEntries, shots_per_step, table) -> StepEntries:
    """The entries with one entry of weight 0 added for every step of a peak's band
    ``band = (step_lo, step_hi)`` ((Q,) each) that has valid shots but no entry, in
    bands of at least :data:`DENSE_BAND_SHOTS` shots per step (at code 1: with no
    detection its expected background, :func:`window_background`, does not depend
    on the code), sorted by (peak, step, code).  ``table``: its ``theta_min``,
    ``step`` and ``n_steps`` are read."""
    lo_s, hi_s = band
    q, step, code, weight = entries.peak, entries.step, entries.code, entries.weight
    theta = table.theta_min + step * table.step
    if q.size == 0:
        return StepEntries(q, step, code, weight, theta)
    S = table.n_steps
    lo_s = np.clip(np.asarray(lo_s, np.int64), 0, S - 1)
    hi_s = np.clip(np.asarray(hi_s, np.int64), -1, S - 1)
    n = np.maximum(hi_s - lo_s + 1, 0)
    qb = np.repeat(np.arange(n.size), n)
    sb = lo_s[qb] + np.arange(qb.size) - np.repeat(np.cumsum(n) - n, n)
    nsh = np.asarray(shots_per_step)
    if qb.size:
        # only bands whose scan revisits its steps (≥ DENSE_BAND_SHOTS valid shots per
        # valid step on average): there a step without a detection is a measurement
        # with few neighbours like it; where each step is sampled about once most of
        # the band is such steps, and subtracting their background trades the bias
        # for more noise
        valid = nsh[sb] > 0
        per_band = (np.bincount(qb, weights=np.where(valid, nsh[sb], 0), minlength=n.size)
                    / np.maximum(np.bincount(qb, weights=valid, minlength=n.size), 1))
        has = (is_in(qb * S + sb, q * S + step) | ~valid
               | (per_band[qb] < DENSE_BAND_SHOTS))
        qb, sb = qb[~has], sb[~has]
    if qb.size == 0:
        return StepEntries(q, step, code, weight, theta)
    q2 = np.concatenate([q, qb])
    s2 = np.concatenate([step, sb])
    c2 = np.concatenate([np.asarray(code, np.int64), np.ones(qb.size, np.int64)])
    w2 = np.concatenate([np.asarray(weight, np.float64), np.zeros(qb.size)])
    o = np.lexsort((c2, s2, q2))
    q2, s2, c2, w2 = q2[o], s2[o], c2[o], w2[o]
    return StepEntries(q2, s2, c2, w2, table.theta_min + s2 * table.step)


@dataclass(frozen=True, eq=False)
class BackgroundSubtraction:
    """What the background subtraction of a run's counted entries reads.

    peaks : a mapping of (Q,) arrays ``row``, ``col``, ``code_lo``, ``code_hi``,
        ``rate_hz`` (Hz) and optionally ``step_lo``, ``step_hi``.
    table : the run's interval table (its ``lo``, ``hi``, ``n_steps``, grid).
    shots_per_step : (S,) int, valid shots per angle step.
    width : the receiver's width, pixels; bin_width : the TDC's bin width, s.
    """

    peaks: Mapping
    table: object
    shots_per_step: np.ndarray
    width: int
    bin_width: float

    def windows(self, q, step) -> CodeWindows:
        """The counted codes of entries of peaks ``q`` at steps ``step`` (M,)."""
        peaks, table = self.peaks, self.table
        pix = peaks.row[q] * self.width + peaks.col[q]
        lo = table.lo[step, pix].astype(np.int64)
        hi = table.hi[step, pix].astype(np.int64)
        return CodeWindows(lo, np.maximum(lo, peaks.code_lo[q]),
                           np.minimum(hi, peaks.code_hi[q]),
                           np.asarray(self.shots_per_step)[step])

    def window_entries(self, counted: StepEntries) -> FusionEntries:
        """Sub-pass 1's entries: the counted ones (weight their float64 counts,
        codes float64) followed by each (peak, step)'s expected background over its
        window, as entries of weight −background at the segments' centroids; each
        entry its own shot, angles per entry.  The background enters the sums as
        negative-weight entries spread over the code interval; its magnitude is the
        Poisson variance of the subtraction (for the σ)."""
        q, step, code = counted.peak, counted.step, counted.code
        weight = counted.weight.astype(np.float64)
        theta = counted.theta
        S = self.table.n_steps
        w = self.windows(q, step)
        first, bgs, cen = window_background(q * S + step, code, weight, w.a, w.b, w.shots,
                                            w.lo, self.peaks.rate_hz[q], self.bin_width)
        J = bgs.shape[1]
        keep = bgs.ravel() > 0
        peak = np.concatenate([q, np.repeat(q[first], J)[keep]])
        return FusionEntries(
            shot=np.arange(peak.size), peak=peak,
            code=np.concatenate([code.astype(np.float64), cen.ravel()[keep]]),
            theta=np.concatenate([theta, np.repeat(theta[first], J)[keep]]),
            weight=np.concatenate([weight, -bgs.ravel()[keep]]),
            background=np.concatenate([np.zeros(q.size), bgs.ravel()[keep]]))

    def inlier_entries(self, acc, counted: StepEntries) -> BackgroundEntries:
        """Sub-pass 2's background of the accumulator ``acc`` (its centres fixed):
        over the codes of each (peak, step) that pass the inlier test
        (:func:`inlier_codes`), at every step of the inliers' angle band (within the
        counted band) that has valid shots, with a detection or not
        (:func:`with_empty_steps`); sub-pass 1's segments stay for the mode and the
        window's detection count (first-photon likelihood)."""
        peaks, S = self.peaks, self.table.n_steps
        band = (acc.band[0], acc.band[1])
        if peaks.step_lo is not None:
            band = (np.maximum(band[0], peaks.step_lo), np.minimum(band[1], peaks.step_hi))
        e = with_empty_steps(band, counted, self.shots_per_step, self.table)
        qe, se = e.peak, e.step
        w = self.windows(qe, se)
        _, g_first, inv = np.unique(qe * S + se, return_index=True, return_inverse=True)
        qg, thg = qe[g_first], e.theta[g_first]

        def margins(gi, c):
            f = acc.fused_ranges(qg[gi], c, thg[gi])
            ctr = acc.centre[f.peak]
            bound = acc.k * f.sigma_r + acc.halfwidth[f.peak]
            bad = ~(f.ok & np.isfinite(ctr))
            return (np.where(bad, np.nan, f.r - (ctr - bound)),
                    np.where(bad, np.nan, ctr + bound - f.r))

        c1, c2 = inlier_codes(margins, w.a[g_first], w.b[g_first])
        a2 = np.maximum(w.a, np.ceil(np.nan_to_num(c1, posinf=1e9, neginf=-1e9))[inv])
        b2 = np.minimum(w.b, np.floor(np.nan_to_num(c2, posinf=1e9, neginf=-1e9))[inv])
        f2, bg2, cen2 = window_background(qe * S + se, e.code, e.weight, a2, b2, w.shots,
                                          w.lo, peaks.rate_hz[qe], self.bin_width)
        kp = bg2.ravel() > 0
        J2 = bg2.shape[1]
        return BackgroundEntries(np.repeat(qe[f2], J2)[kp], cen2.ravel()[kp],
                                 np.repeat(e.theta[f2], J2)[kp], bg2.ravel()[kp])
