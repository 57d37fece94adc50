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

from mems_stereo.errors import GeometryError
from mems_stereo.geometry.uncertainty import (
    Spreads,
    polar_from_cartesian,
)
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import System
from mems_stereo.model.tdc import codes_from_path_length
from mems_stereo.physics.first_photon import _detection_log_odds
from mems_stereo.physics.spot import spot_fraction
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.detections import StereoCache, detection_points
from mems_stereo.pipeline.first_photon_correction import correcting, first_photon_correction
from mems_stereo.pipeline.intervals import interval_table
from mems_stereo.pipeline.pass2 import PeakCounts, decode_peak_keys
from mems_stereo.pipeline.peak_geometry import (
    footprint_halfwidth,
    stereo_angle_jacobian,
    stereo_at_mean_angle,
    stereo_cov_at_mean_angle,
)
from mems_stereo.pipeline.peak_means import PeakMeans, fuse_along_ray
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.sums import PeakSums, RangeMode, add_rows_gathered
from mems_stereo.pipeline.window_background import inlier_codes, window_background


def points_from_counts(system: System, peaks: dict, counts: PeakCounts, settings: Settings,
                       shots_per_step=None, table=None, own=None):
    """The cloud: one fused point per peak from its counted detections.

    Each distinct (peak, step, code) is triangulated once at the step's grid
    angle (the angle it was classified with) and weighted by its count, times
    the probability that a detection at that step is signal when the peaks
    carry ``background_by_step`` (background subtraction in scan angle).
    Peaks whose stereo and ToF ranges disagree are left out
    (:func:`~mems_stereo.pipeline.fusion.consistent_points`).
    ``shots_per_step`` : (S,) int, valid shots per angle step of the interval
    table (:func:`~mems_stereo.pipeline.intervals.shots_per_step`): with it the ToF and
    fused estimates are corrected for the first-photon delay
    (:class:`~mems_stereo.pipeline.fusion.PeakAccumulator`).
    ``table`` : the run's interval table (default: a new one; only its grid is used).
    ``own`` : (a, b) or None, see :meth:`PeakAccumulator.cloud`.
    """
    acc = peak_sums_from_counts(system, peaks, counts, settings, shots_per_step, table)
    return consistent_points(acc.cloud(settings.min_counts, own), settings.confidence)


def accumulator_for_peaks(system: System, peaks: dict, settings: Settings,
                          shots_per_step=None, table=None) -> PeakAccumulator:
    """An empty :class:`PeakAccumulator` of the peaks (a mapping of (Q,) arrays
    ``row``, ``col``, ``code``, optionally ``rate_hz``, ``step_lo``, ``step_hi``)."""
    if table is None:
        table = interval_table(system, settings.confidence, min_range=settings.min_range)
    return PeakAccumulator(system, peaks["row"], peaks["col"], peaks["code"],
                           confidence=settings.confidence, shots_per_step=shots_per_step,
                           step_grid=(table.theta_min, table.step),
                           rate_hz=peaks.get("rate_hz"),
                           step_window=(peaks["step_lo"], peaks["step_hi"])
                           if peaks.get("step_lo") is not None else None,
                           accept=_acceptance(system, table, peaks))


def peak_sums_from_counts(system: System, peaks: dict, counts: PeakCounts, settings: Settings,
                          shots_per_step=None, table=None) -> PeakAccumulator:
    """The :class:`PeakAccumulator` of the peaks after both sub-passes over their
    counted entries (arguments as :func:`points_from_counts`, whose cloud is
    ``acc.cloud(settings.min_counts)``).  The sums of a peak are its entries'
    alone: the accumulators of blocks of peaks joined
    (:meth:`PeakAccumulator.joined`) are the whole's, bit for bit."""
    if table is None:
        table = interval_table(system, settings.confidence, min_range=settings.min_range)
    S, nb = table.n_steps, system.tdc.n_bins + 1
    k = counts.keys
    q, step, code = decode_peak_keys(k, S, nb)
    theta = table.theta_min + step * table.step
    weight = counts.counts.astype(np.float64)
    background = None
    inlier_background = None
    rate = peaks.get("rate_hz")
    q_all, code_all, theta_all = q, code.astype(np.float64), theta
    if rate is not None and shots_per_step is not None and k.size:
        # background subtraction: each (peak, step)'s expected background enters
        # as negative-weight entries spread over its code interval
        # (:func:`window_background`); their magnitude is the Poisson variance
        # of the subtraction (for the σ)
        W = system.receiver.width

        def entry_geometry(qe, se):
            pix = peaks["row"][qe] * W + peaks["col"][qe]
            lo = table.lo[se, pix].astype(np.int64)
            hi = table.hi[se, pix].astype(np.int64)
            return (lo, np.maximum(lo, peaks["code_lo"][qe]),
                    np.minimum(hi, peaks["code_hi"][qe]), np.asarray(shots_per_step)[se])

        lo, a, b, n_shots = entry_geometry(q, step)
        first, bgs, cen = window_background(q * S + step, code, weight, a, b, n_shots, lo,
                                            rate[q], system.tdc.bin_width)
        q0, step0, code0, weight0 = q, step, code, counts.counts
        J = bgs.shape[1]
        keep = bgs.ravel() > 0
        q_all = np.concatenate([q, np.repeat(q[first], J)[keep]])
        code_all = np.concatenate([code_all, cen.ravel()[keep]])
        theta_all = np.concatenate([theta, np.repeat(theta[first], J)[keep]])
        background = np.concatenate([np.zeros(k.size), bgs.ravel()[keep]])
        weight = np.concatenate([weight, -bgs.ravel()[keep]])

        def inlier_background(acc):
            # sub-pass 2's background: over the codes of each (peak, step) that pass
            # the inlier test (:func:`inlier_codes`), at every step of the inliers'
            # angle band (within the counted band) that has valid shots, with a
            # detection or not (:func:`_with_empty_steps`); the segments above stay
            # for the mode and the window's detection count (first-photon likelihood)
            band = {"step_lo": acc.band[0], "step_hi": acc.band[1]}
            if peaks.get("step_lo") is not None:
                band = {"step_lo": np.maximum(band["step_lo"], peaks["step_lo"]),
                        "step_hi": np.minimum(band["step_hi"], peaks["step_hi"])}
            qe, se, ce, we, te = _with_empty_steps(band, q0, step0, code0, weight0,
                                                   shots_per_step, table)
            lo_e, a_e, b_e, n_e = entry_geometry(qe, se)
            _, g_first, inv = np.unique(qe * S + se, return_index=True, return_inverse=True)
            qg, thg = qe[g_first], te[g_first]

            def margins(gi, c):
                pk, r, sr, ok = acc._fused_ranges(qg[gi], c, thg[gi])
                ctr = acc.centre[pk]
                bound = acc.k * sr + acc.halfwidth[pk]
                bad = ~(ok & np.isfinite(ctr))
                return (np.where(bad, np.nan, r - (ctr - bound)),
                        np.where(bad, np.nan, ctr + bound - r))

            c1, c2 = inlier_codes(margins, a_e[g_first], b_e[g_first])
            a2 = np.maximum(a_e, np.ceil(np.nan_to_num(c1, posinf=1e9, neginf=-1e9))[inv])
            b2 = np.minimum(b_e, np.floor(np.nan_to_num(c2, posinf=1e9, neginf=-1e9))[inv])
            f2, bg2, cen2 = window_background(qe * S + se, ce, we, a2, b2, n_e, lo_e, rate[qe],
                                              system.tdc.bin_width)
            kp = bg2.ravel() > 0
            J2 = bg2.shape[1]
            return (np.repeat(qe[f2], J2)[kp], cen2.ravel()[kp],
                    np.repeat(te[f2], J2)[kp], bg2.ravel()[kp])

    acc = accumulator_for_peaks(system, peaks, settings, shots_per_step, table)
    return accumulate_entries(acc, np.arange(q_all.size), q_all, code_all, theta_all,
                              weight=weight, background=background,
                              inlier_background=None if background is None
                              else inlier_background)


#: fewest valid shots per valid angle step, on average over a peak's band, for the
#: background of its steps without a detection to be subtracted (:func:`_with_empty_steps`;
#: as ``first_photon_correction.BINOMIAL_MIN_SHOTS``: a scan that revisits its angles)
DENSE_BAND_SHOTS = 2.0


def _is_in(a, b) -> np.ndarray:
    """``np.isin(a, b)`` (int64 arrays); by binary search where ``b`` is sorted (the
    fusion's entries are, by peak and step), without sorting both arrays."""
    b = np.asarray(b)
    if b.size == 0 or not bool(np.all(b[1:] >= b[:-1])):
        return np.isin(a, b)
    i = np.minimum(np.searchsorted(b, a), b.size - 1)
    return b[i] == a


def _with_empty_steps(band, q, step, code, weight, shots_per_step, table):
    """The entries (q, step, code, weight, theta), each (M',), with one entry of
    weight 0 added for every step of a peak's band ``[step_lo, step_hi]`` (a
    mapping of (Q,) arrays) that has valid shots but no entry, in bands of at
    least :data:`DENSE_BAND_SHOTS` shots per step (at code 1: with
    no detection its expected background, :func:`window_background`, does not
    depend on the code), sorted by (peak, step, code)."""
    lo_s, hi_s = band["step_lo"], band["step_hi"]
    theta = table.theta_min + step * table.step
    if q.size == 0:
        return q, step, code, weight, theta
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
        # for more noise (the floodlight sample, 1.27 shots per step: its 132 common
        # points' median error 2.04 -> 2.16 cm, 4 points lost)
        valid = nsh[sb] > 0
        per_band = (np.bincount(qb, weights=np.where(valid, nsh[sb], 0), minlength=n.size)
                    / np.maximum(np.bincount(qb, weights=valid, minlength=n.size), 1))
        has = (_is_in(qb * S + sb, q * S + step) | ~valid
               | (per_band[qb] < DENSE_BAND_SHOTS))
        qb, sb = qb[~has], sb[~has]
    if qb.size == 0:
        return q, step, code, weight, theta
    q2 = np.concatenate([q, qb])
    s2 = np.concatenate([step, sb])
    c2 = np.concatenate([np.asarray(code, np.int64), np.ones(qb.size, np.int64)])
    w2 = np.concatenate([np.asarray(weight, np.float64), np.zeros(qb.size)])
    o = np.lexsort((c2, s2, q2))
    q2, s2, c2, w2 = q2[o], s2[o], c2[o], w2[o]
    return q2, s2, c2, w2, table.theta_min + s2 * table.step


def _acceptance(system: System, table, peaks):
    """accept(steps (Q, B), centre (Q,) m, q=None) -> (Q, B) bool (rows: the peaks ``q``,
    default all): whether the code of a return
    from the peak's centre range, at each step's grid angle, lies in the pixel's
    accepted interval (else the classifier labels it noise: such shots are
    neither hits nor misses of the first-photon likelihood)."""
    W = system.receiver.width
    pix = (peaks["row"] * W + peaks["col"]).astype(np.int64)

    def accept(steps, centre, q=None):
        px = pix if q is None else pix[q]
        th = table.theta_min + steps * table.step
        d = scan_direction(th.ravel(), system.scanner)
        p = np.asarray(system.scanner.position, dtype=np.float64)
        pd = d @ p
        r = np.broadcast_to(np.asarray(centre, np.float64)[:, None], steps.shape).ravel()
        with np.errstate(invalid="ignore"):
            s = -pd + np.sqrt(pd * pd - p @ p + r ** 2)
        code = np.floor(codes_from_path_length(s + r, system.tdc, system.speed_of_light))
        code = code.reshape(steps.shape)
        table.ensure(np.unique(steps))
        lo = table.lo[steps, px[:, None]]
        hi = table.hi[steps, px[:, None]]
        return (code >= lo) & (code <= hi)

    return accept


class PeakAccumulator:
    """Streaming fusion of each peak's signal detections into one point.

    Two sub-passes over the detections (each in chunks of any size, in any
    order, on any number of workers — accumulators add with ``+``):

    1. :meth:`add_mode` — every detection adds its range interval
       ``[r_i − σ_i, r_i + σ_i]`` (fused range and its σ) to a coverage count
       on a logarithmic range grid (relative step ``rel_step``).  The peak's
       centre is the range covered by most intervals (:meth:`finish_mode`):
       a mode, robust to background that passed the classifier inside the
       window, whose stereo ranges spread over metres while true returns
       cluster within their σ; a sharp cluster of few near-range background
       detections cannot outvote a broader cluster of many true returns.
    2. :meth:`add_inliers` — detections within ``k·σ_i`` of the centre add
       their fused, stereo and time-of-flight points and covariances to
       per-peak sums.

    :meth:`cloud` returns, for each estimate (fused, stereo, time of flight),
    the mean weighted by the inverse of the estimate's own range variance
    (time of flight: equal weights, every detection has the same timing spread),
    ``x̄ = Σ w_i x_i / Σ w_i`` with covariance ``Σ w_i² C_i / (Σ w_i)²``, scaled
    by the inliers' reduced χ² when it exceeds 1 (Birge ratio: the reported σ
    stays honest when the scatter exceeds the propagated spread).  Memory is
    O(peaks × grid), independent of the number of detections.

    First-photon correction of the time-of-flight estimate (``first_photon``,
    on by default; it needs ``shots_per_step`` and ``step_grid``, the valid
    shots per scan-angle step of the interval table's grid, and is skipped
    without them).  A SPAD records the first photon of a shot, so a strong
    return arrives early (δ ≈ −0.6 ns at μ = 0.35 photons per shot, −1.8 ns at
    1, −5.9 ns at 4 with the 14.9 ns pulse) and one at the TDC start late
    (:func:`first_photon_moments`).  μ comes from which shots fired: a shot
    at angle θ puts the share ``f(θ)`` of the spot on the pixel
    (:func:`spot_fraction`, target at the peak's centre range) and fires with
    ``p = 1 − exp(−μ0·f)``.  Each inlier adds its log-odds on a grid of μ0
    (:data:`MU_GRID`, :meth:`add_inliers`); at :meth:`cloud` the steps
    around the inliers' angle band add ``N_s·ln(1 − p_s)`` for every valid
    shot; the posterior of μ0 (uniform in log μ0) gives the expected delay
    of the detections' mean (:func:`first_photon_delay`).  The spot profile
    carries the information a saturated detection rate (every shot fires)
    lacks: the stronger the return, the further outside the pixel the spot
    still fires it.  The delay is removed from the ToF mean (the fused mean
    moves by its ToF share), a detection's timing variance becomes the
    first-photon one, and the posterior spread of the delay is added in
    quadrature (after the Birge scaling).  Assumptions: the spot model
    (Gaussian, ``spot_sigma``; default the simulator's
    :class:`~mems_stereo.physics.spot.SpotModel` at the peak's range), the
    background inside the window subtracted (:func:`window_background`), the
    target's range constant across the band, a Gaussian pulse of the
    system's ``pulse_fwhm`` ⊕ the spreads' jitter.
    """

    def __init__(self, system: System, rows, cols, peak_code=None,
                 spreads: Spreads | None = None, confidence: float = 0.997,
                 r_min: float = 0.01, r_max: float = 1000.0, rel_step: float = 2e-3,
                 shots_per_step=None, step_grid=None, first_photon: bool = True,
                 spot_sigma: float | None = None, rate_hz=None, step_window=None,
                 accept=None):
        from mems_stereo.pipeline.consistency import k_from_confidence

        self.system = system
        self.shots_per_step = (None if shots_per_step is None or step_grid is None
                               else np.asarray(shots_per_step, dtype=np.int64).ravel())
        self.step_grid = None if step_grid is None else (float(step_grid[0]),
                                                         float(step_grid[1]))
        self.first_photon = bool(first_photon)
        self.spot_sigma = None if spot_sigma is None else float(spot_sigma)
        self.spreads = spreads
        self.k = k_from_confidence(confidence)
        self.rows = np.asarray(rows, dtype=np.int64).ravel()
        self.cols = np.asarray(cols, dtype=np.int64).ravel()
        if self.rows.shape != self.cols.shape:
            raise GeometryError("rows, cols: expected equal lengths")
        self.peak_code = None if peak_code is None else np.asarray(peak_code, np.float64)
        self.Q = self.rows.size
        # (step_lo, step_hi) (Q,) each: the steps pass 2 counted; accept(steps (Q, B),
        # centre (Q,)) -> (Q, B) bool: steps where the return's code is classified signal
        self.step_window = step_window
        self.accept = accept
        self.rate_hz = (np.zeros(self.Q) if rate_hz is None
                        else np.nan_to_num(np.asarray(rate_hz, np.float64).ravel()))
        self.mode = RangeMode(self.Q, r_min, r_max, rel_step)
        self.centre = None
        Q = self.Q
        self.sums = PeakSums.zeros(Q)
        self.band = _empty_band(Q)  # inliers' angle steps: min, max (merged, not summed)

    def empty_copy(self) -> PeakAccumulator:
        """A zeroed accumulator of the same peaks and grid (keeps the centres)."""
        new = object.__new__(PeakAccumulator)
        new.__dict__.update(self.__dict__)
        new.mode = self.mode.zeroed()
        new.sums = PeakSums.zeros(self.Q)
        new.band = _empty_band(self.Q)
        return new

    def __add__(self, other: PeakAccumulator) -> PeakAccumulator:
        new = self.empty_copy()
        new.mode = self.mode + other.mode
        new.sums = self.sums + other.sums
        new.band = (np.minimum(self.band[0], other.band[0]),
                    np.maximum(self.band[1], other.band[1]))
        return new

    def joined(self, parts) -> PeakAccumulator:
        """This accumulator's peaks with the state of ``parts``, accumulators of
        consecutive blocks of its peaks (in order, covering all of them) after
        their sub-passes: centres, inlier bounds, angle bands and sums are per
        peak, so the result is the one accumulator of every entry, bit for bit."""
        new = self.empty_copy()
        if sum(p.Q for p in parts) != self.Q:
            raise GeometryError(f"joined: the parts hold {sum(p.Q for p in parts)} peaks, "
                                f"expected {self.Q}")
        new.centre = np.concatenate([p.centre for p in parts])
        new.halfwidth = np.concatenate([p.halfwidth for p in parts])
        new.band = tuple(np.concatenate([p.band[i] for p in parts]) for i in (0, 1))
        new.sums = PeakSums.concat([p.sums for p in parts])
        return new

    def _points(self, shot, peak, code, theta, weight):
        shot = np.asarray(shot, dtype=np.int64).ravel()
        peak = np.asarray(peak, dtype=np.int64).ravel()
        code = np.asarray(code, dtype=np.float64).ravel()
        w = (np.ones(shot.shape) if weight is None
             else np.asarray(weight, dtype=np.float64).ravel())
        if not (shot.shape == peak.shape == code.shape == w.shape):
            raise GeometryError("shot, peak, code, weight: expected equal lengths")
        dp = detection_points(self.system, shot, self.rows[peak], self.cols[peak], code, theta,
                              self.spreads, stereo_cache=self._stereo_cache())
        r, _, sr, _ = polar_from_cartesian(dp.fused, dp.cov_fused)
        ok = dp.ok & np.isfinite(r) & np.isfinite(sr) & (sr > 0)
        return peak, code, dp, r, sr, ok, w

    def _stereo_cache(self) -> StereoCache:
        """The stereo geometry of the (pixel, step) runs this accumulator has evaluated
        (its sub-passes and inlier margins meet each several times)."""
        if getattr(self, "_stereo", None) is None:
            self._stereo = StereoCache()
        return self._stereo

    def _fused_ranges(self, peak, code, theta):
        """``(peak, r, sr, ok)`` of :meth:`_points` for entries at angles ``theta`` (M,)
        (the same bits), from the fused points alone (no stereo or ToF covariances)."""
        peak = np.asarray(peak, dtype=np.int64).ravel()
        code = np.asarray(code, dtype=np.float64).ravel()
        x, C, ok = detection_points(self.system, np.arange(peak.size), self.rows[peak],
                                    self.cols[peak], code, theta, self.spreads,
                                    fused_only=True, stereo_cache=self._stereo_cache())
        # r and σ_r as polar_from_cartesian computes them
        r = np.linalg.norm(x, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            gr = x / r[:, None]
        sr = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", gr, C, gr), 0.0))
        ok = ok & np.isfinite(r) & np.isfinite(sr) & (sr > 0)
        return peak, r, sr, ok

    def add_mode(self, shot, peak, code, theta, weight=None) -> None:
        """Sub-pass 1: coverage of each detection's ±σ range interval.

        ``shot, peak, code`` (M,) int; ``theta`` (K,) rad indexed by ``shot``;
        ``weight`` (M,) multiplicities (default 1): identical detections
        counted once with their number, possibly scaled by their probability
        of being signal.
        """
        self._add_mode_points(self._points(shot, peak, code, theta, weight))

    def _add_mode_points(self, pts) -> None:
        peak, _, _, r, sr, ok, w = pts
        self.mode.add(peak[ok], r[ok], sr[ok], w[ok])

    def finish_mode(self) -> np.ndarray:
        """Fix each peak's centre range (Q,) m (NaN without detections) and the
        inliers' half-width (:class:`RangeMode`)."""
        self.centre, self.halfwidth = self.mode.finish()
        self.halfwidth = np.maximum(self.halfwidth, footprint_halfwidth(
            self.system, self.rows, self.cols, self.centre, self.spreads))
        return self.centre

    def add_inliers(self, shot, peak, code, theta, weight=None, background=None) -> None:
        """Sub-pass 2: sums over the detections within k·σ of their peak's centre
        (arguments as :meth:`add_mode`).

        ``background`` (M,) : the expected background detections that were
        subtracted at each entry (its share of its angle step's expected
        background).  Their Poisson fluctuation is the uncertainty of the
        subtraction; it adds ``Σ b_i (r_i − r̄)² / (Σ m_i)²`` to the range
        variance of the stereo mean (r: the entries' fused ranges) and of the
        time-of-flight mean (r: their ToF ranges).
        """
        if self.centre is None:
            raise RuntimeError("add_inliers before finish_mode")
        self._add_inliers_points(self._points(shot, peak, code, theta, weight), shot, theta,
                                 background)

    def _add_inliers_points(self, pts, shot, theta, background) -> None:
        # every per-peak sum is sequential in entry order (np.add.at), so adding the
        # entries in blocks gives the sums of adding them at once, bit for bit
        peak, code, dp, r, sr, ok, m = pts
        self._add_inliers_sums(peak, code, r, sr, ok, m, lambda inl: dp.subset(inl), shot,
                               theta, background)

    def _add_inliers_sums(self, peak, code, r, sr, ok, m, dp_of, shot, theta,
                          background, may_be_inlier=None, count_window=True) -> None:
        """The sums of :meth:`add_inliers` from each entry's fused range r, its σ sr and
        ok (M,); ``dp_of(inl)`` gives the :class:`DetectionPoints` of the inliers only
        (each entry's points are its own: computing them for the inliers alone
        changes no bit)."""
        s = self.sums
        if count_window:
            np.add.at(s.window, peak, m)
        with np.errstate(invalid="ignore"):
            inl = ok & (np.abs(r - self.centre[peak]) <= self.k * sr + self.halfwidth[peak])
        if may_be_inlier is not None:
            inl &= may_be_inlier
        q = peak[inl]
        m_all, m = m, m[inl]
        np.add.at(s.n, q, m)
        np.add.at(s.detections, q, np.maximum(m, 0.0))
        dp = dp_of(inl)
        # equal weights: inside one peak the spread of the estimates is the pixel's
        # footprint swept by the beam (stereo) or the pulse (ToF), and their σ grows
        # with the value itself (stereo σ ∝ r²; a ToF point near the mirror has a
        # tiny range variance): inverse-variance weights would pull every peak
        # towards its nearest detections.  ∂x/∂L: the ToF point's, the fused
        # point's share of it.
        g = dp.dtof_dL
        s.fused.add(q, dp.fused, dp.cov_fused, m,
                    g * (1.0 - dp.weight_stereo)[:, None])
        s.stereo.add(q, dp.stereo, dp.cov_stereo, m)
        s.tof.add(q, dp.tof, dp.cov_tof, m, g)
        if self.shots_per_step is not None and self.first_photon and peak.size and count_window:
            # band: the inliers' steps; likelihood: every detection of the window (the
            # in-peak test drops true returns at the band's edges, where the spot is
            # half off the pixel: counting those shots as misses would bias μ0 low)
            th = np.asarray(theta, dtype=np.float64)[np.asarray(shot, np.int64).ravel()]
            t0, dt = self.step_grid
            st = np.rint((th[inl] - t0) / dt).astype(np.int64)
            np.minimum.at(self.band[0], q, st)
            np.maximum.at(self.band[1], q, st)
            # the log-odds depend on (peak, θ) alone: once per run of equal (peak, θ)
            # (the entries of one (peak, step) are consecutive), gathered per entry
            new = np.ones(peak.size, bool)
            new[1:] = (peak[1:] != peak[:-1]) | (th[1:] != th[:-1])
            start = np.flatnonzero(new)
            ps = peak[start]
            f = spot_fraction(self.system, self.rows[ps], self.cols[ps], th[start],
                              self.centre[ps], self.spot_sigma)
            run = np.cumsum(new) - 1
            add_rows_gathered(s.loglik, peak, _detection_log_odds(f), run, m_all)
        w = 1.0 / sr[inl] ** 2  # for the scatter test: residuals in units of their σ
        th_e = np.asarray(theta, dtype=np.float64)[np.asarray(shot, np.int64).ravel()][inl]
        np.add.at(s.theta, q, m * th_e)
        np.add.at(s.code, q, m * code[inl])
        np.add.at(s.weight, q, m * dp.weight_stereo)
        np.add.at(s.w, q, m * w)
        np.add.at(s.wr, q, m * w * r[inl])
        np.add.at(s.wrr, q, m * w * r[inl] ** 2)
        if background is not None:  # (the means have equal weights)
            b = np.asarray(background, dtype=np.float64).ravel()[inl]
            np.add.at(s.b0, q, b)
            # the stereo mean is taken at the mean angle: its background variance
            # is that of the mean angle (see :meth:`peak_means`)
            np.add.at(s.b1, q, b * th_e)
            np.add.at(s.b2, q, b * th_e ** 2)
            r_tof = np.linalg.norm(dp.tof, axis=1)
            np.add.at(s.bt1, q, b * r_tof)
            np.add.at(s.bt2, q, b * r_tof ** 2)

    def cloud(self, min_counts: int = 1, own=None) -> PointCloud:
        """One point per peak with at least ``min_counts`` inliers (see class docstring).

        ``own`` : (a, b) or None — points of peaks a..b−1 only; the others are the
        block's halo, fused so that the depth edges of its own peaks see every
        neighbour (:func:`mems_stereo.pipeline.run.points_block`)."""
        return self.peak_means().cloud(min_counts, own)

    def peak_means(self) -> PeakMeans:
        """Each peak's stereo and ToF means with every term of their σ (scatter,
        pixel location, background, first-photon model): all of :meth:`cloud` that
        is the peak's own (the first-photon step by blocks of :data:`FP_BLOCK`
        peaks by index); the depth edges, which look at the row neighbours, are
        :meth:`PeakMeans.cloud`'s.  The means of blocks of peaks cut at multiples
        of ``FP_BLOCK``, joined (:meth:`PeakMeans.concat`), are the whole's."""
        s = self.sums
        n = s.n
        with np.errstate(invalid="ignore", divide="ignore"):
            # means x̄ = Σ w x / Σ w, covariance Σ w² C / (Σ w)² (w: multiplicities)
            mean = {name: s.estimate(name).mean() for name in ("fused", "stereo", "tof")}
            W = s.fused.W
            # reduced χ² of the fused ranges about their σ-weighted mean:
            # Σ w (r_i − r̄)² = Σ w r² − 2 r̄ Σ w r + r̄² Σ w, w = 1/σ_i²
            rbar_w = s.wr / s.w
            chi2 = (s.wrr - 2 * rbar_w * s.wr + rbar_w ** 2 * s.w) / np.maximum(n - 1, 1)
            x_tof = mean["tof"][0]  # before the first-photon correction: the entries' mean
            rbar_t = np.linalg.norm(x_tof, axis=1)
            var_bg_t = np.maximum(s.bt2 - 2 * rbar_t * s.bt1 + rbar_t ** 2 * s.b0, 0.0) / W ** 2
            u_t = x_tof / rbar_t[:, None]
        birge = np.where(n > 2, np.maximum(1.0, np.nan_to_num(chi2, nan=1.0)), 1.0)
        grid = None if self.step_grid is None else self.step_grid[1]
        c_pix, range_per_px = stereo_at_mean_angle(self.system, self.rows, self.cols,
                                                   self.sums.theta, n, mean, step=grid)
        # its covariance: the mean angle's, propagated at that angle (the detections
        # and the subtracted background count as independent entries, as in the sums)
        C_st = stereo_cov_at_mean_angle(self.system, self.rows, self.cols, s.theta, n,
                                        s.detections + s.b0, self.spreads)
        okc = np.all(np.isfinite(C_st), axis=(1, 2))
        mean["stereo"] = (mean["stereo"][0],
                          np.where(okc[:, None, None], C_st, mean["stereo"][1]))
        # the first-photon correction needs the pulse's centre: from the peak-level
        # fusion of the stereo (at the mean angle) and uncorrected ToF means
        mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])[:2]
        fp = first_photon_correction(self, mean) if correcting(self) else None
        if fp is not None:  # the stereo at the mean angle less its expected bias
            # removed where significant: beyond k of the mean angle's statistical σ
            # (below it the correction is within the noise, and it rests on the
            # system's geometry: a wrong system, e.g. the samples' nominal one,
            # predicts wrong small biases); where not removed it stays in σ
            with np.errstate(invalid="ignore", divide="ignore"):
                Jt = stereo_angle_jacobian(self.system, self.rows, self.cols, s.theta / n)
                sig_th = np.sqrt(np.einsum("qi,qij,qj->q", Jt, mean["stereo"][1], Jt)
                                 * birge) / np.einsum("qi,qi->q", Jt, Jt)
                removed = np.abs(fp["angle_bias"]) > self.k * np.nan_to_num(sig_th, nan=np.inf)
            c_pix, range_per_px = stereo_at_mean_angle(self.system, self.rows, self.cols,
                                                       self.sums.theta, n, mean,
                                                       angle_bias=fp["angle_bias"], step=grid,
                                                       removed=removed)
        # the stereo mean's spread is that of its mean scan angle: binomial, not
        # Poisson, where the scan revisits its angles (angle_binomial_factor)
        scale = {"stereo": birge if fp is None else birge * fp["angle_binomial"],
                 "tof": birge}
        for name in ("stereo", "tof"):
            mean[name] = (mean[name][0], mean[name][1] * scale[name][:, None, None])
        for name, C in (c_pix or {}).items():  # systematic: not scaled
            mean[name] = (mean[name][0], mean[name][1] + C)
        # the subtracted background's Poisson fluctuation moves the mean angle:
        # Σ b (θ_b − θ̄)² / n², along ∂x/∂θ at the mean angle
        with np.errstate(invalid="ignore", divide="ignore"):
            th_bar = s.theta / n
            var_th = np.maximum(s.b2 - 2 * th_bar * s.b1 + th_bar ** 2 * s.b0, 0.0) / W ** 2
        Jt = stereo_angle_jacobian(self.system, self.rows, self.cols, th_bar)
        add = np.nan_to_num(var_th)[:, None, None] * Jt[:, :, None] * Jt[:, None, :]
        mean["stereo"] = (mean["stereo"][0], mean["stereo"][1] + np.nan_to_num(add))
        # the same for the time of flight: far away (stereo of no weight) a peak under
        # strong background is its ToF, and the background's Poisson fluctuation
        # across the accepted code interval (metres of range) is most of its error
        add_t = np.nan_to_num(var_bg_t)[:, None, None] * u_t[:, :, None] * u_t[:, None, :]
        mean["tof"] = (mean["tof"][0], mean["tof"][1] + np.nan_to_num(add_t))
        if fp is not None:  # the delay's posterior spread: systematic, not scaled
            D = s.tof.dL()[0]
            mean["tof"] = (mean["tof"][0], mean["tof"][1] + D[:, :, None] * D[:, None, :]
                           * (fp["sigma_L"] ** 2)[:, None, None])
        # the point: the peak's stereo and ToF means, each with every term of its σ
        # (scatter, pixel location, background, first-photon model), combined by
        # their range variances (a stereo mean near the beam's vanishing point,
        # σ of metres, then leaves the ToF alone instead of dragging the mean)
        mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])
        return PeakMeans(self.system, self.k, self.rows, self.cols, self.peak_code,
                         mean["stereo"], mean["tof"], n, s.detections, s.window, s.code,
                         birge, range_per_px,
                         None if fp is None else fp["delay"], None if fp is None else fp["mu"])




def _empty_band(Q: int):
    return (np.full(Q, np.iinfo(np.int64).max, np.int64), np.full(Q, -1, np.int64))


def points_from_peak_detections(system: System, shot, peak, code, theta, rows, cols,
                                peak_code=None, spreads: Spreads | None = None,
                                min_counts: int = 1, confidence: float = 0.997,
                                weight=None, background=None, shots_per_step=None, step_grid=None,
                                first_photon: bool = True, rate_hz=None, step_window=None,
                                accept=None, spot_sigma: float | None = None,
                                own=None) -> PointCloud:
    """One fused point per peak from the signal detections inside its code window.

    In-memory form of :class:`PeakAccumulator` (same result as streaming it).

    Parameters
    ----------
    shot, peak, code : (M,) int — each detection's shot index, the index of
        its peak (0..Q−1) and its TDC code.
    theta : (K,) rad, scan angle of every shot.
    rows, cols : (Q,) int, pixel of each peak; peak_code : (Q,) the
        detector's peak code (kept as the ``code`` attribute when given).
    min_counts : peaks with fewer inlier detections are dropped.
    confidence : sets the inlier bound ``k`` around each peak's centre.
    weight : (M,) multiplicity of each detection (default 1).
    background : (M,) expected background subtracted at each entry (optional;
        see :meth:`PeakAccumulator.add_inliers`).
    shots_per_step : (S,) int, valid shots per scan-angle step of the grid
        ``step_grid = (theta_min, dtheta)`` (rad; the interval table's,
        :func:`~mems_stereo.pipeline.intervals.shots_per_step`): with both (and
        ``first_photon``) the ToF
        and fused estimates are corrected for the first-photon delay (see
        :class:`PeakAccumulator`) and the cloud gains ``tof_delay`` (s, the
        delay removed) and ``signal_photons`` (μ0 per shot); without them
        the result is the uncorrected one.
    first_photon : apply that correction when the data allow it.
    """
    acc = PeakAccumulator(system, rows, cols, peak_code, spreads, confidence,
                          shots_per_step=shots_per_step, step_grid=step_grid,
                          first_photon=first_photon, rate_hz=rate_hz,
                          step_window=step_window, accept=accept, spot_sigma=spot_sigma)
    return accumulate_entries(acc, shot, peak, code, theta, weight, background).cloud(
        min_counts, own)


def accumulate_entries(acc: PeakAccumulator, shot, peak, code, theta, weight=None,
                       background=None, inlier_background=None) -> PeakAccumulator:
    """Both sub-passes of ``acc`` over the entries (arguments as
    :func:`points_from_peak_detections`); returns ``acc``, its centres fixed and its
    sums added.

    ``inlier_background`` (optional): ``f(acc) -> (peak, code, theta, background)``
    (N,) each, called after the centres are fixed: sub-pass 2's background
    entries (weight −background) in place of the entries with ``background > 0``,
    which then count only in the window (the first-photon likelihood)."""
    system = acc.system
    shot = np.asarray(shot, dtype=np.int64).ravel()
    M = shot.size
    bg = None if background is None else np.asarray(background, np.float64).ravel()
    may = None if inlier_background is None or bg is None else ~(bg > 0)
    if M <= ENTRY_BLOCK:  # the entries' points computed once, used by both sub-passes
        pts = acc._points(shot, peak, code, theta, weight)
        acc._add_mode_points(pts)
        acc.finish_mode()
        if may is None:
            acc._add_inliers_points(pts, shot, theta, background)
        else:
            pe, ce, dp, r, sr, ok, m = pts
            acc._add_inliers_sums(pe, ce, r, sr, ok, m, lambda inl: dp.subset(inl), shot,
                                  theta, bg, may_be_inlier=may)
            _add_inlier_background(acc, inlier_background(acc))
        acc._stereo = None  # (the sub-passes' stereo geometry: no longer needed)
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
        pe, r[e], sr[e], ok[e] = acc._fused_ranges(peak[e], code[e], th[shot[e]])
        acc._add_mode_points((pe, None, None, r[e], sr[e], ok[e], m[e]))
    acc.finish_mode()
    for a in range(0, M, ENTRY_BLOCK):
        e = slice(a, a + ENTRY_BLOCK)
        pe, ce, se = peak[e], code[e], shot[e]

        def dp_of(inl, pe=pe, ce=ce, se=se):
            return detection_points(system, se[inl], acc.rows[pe[inl]], acc.cols[pe[inl]],
                                    ce[inl], theta, acc.spreads,
                                    stereo_cache=acc._stereo_cache())

        acc._add_inliers_sums(pe, ce, r[e], sr[e], ok[e], m[e], dp_of, se, theta,
                              None if bg is None else bg[e],
                              may_be_inlier=None if may is None else may[e])
    if may is not None:
        _add_inlier_background(acc, inlier_background(acc))
    acc._stereo = None
    return acc


def _add_inlier_background(acc: PeakAccumulator, entries) -> None:
    """Sub-pass 2 over background entries ``(peak, code, theta, background)`` (N,)
    each: weight −background, inlier sums only (not the window), in blocks."""
    peak, code, theta, b = entries
    for a in range(0, peak.size, ENTRY_BLOCK):
        e = slice(a, a + ENTRY_BLOCK)
        sh = np.arange(peak[e].size)
        pe, ce, te = peak[e], code[e], theta[e]
        _, r, sr, ok = acc._fused_ranges(pe, ce, te)

        def dp_of(inl, pe=pe, ce=ce, te=te):  # the inliers' points alone (the same bits)
            return detection_points(acc.system, np.arange(int(inl.sum())), acc.rows[pe[inl]],
                                    acc.cols[pe[inl]], ce[inl], te[inl], acc.spreads,
                                    stereo_cache=acc._stereo_cache())

        acc._add_inliers_sums(pe, ce, r, sr, ok, -b[e], dp_of, sh, te, b[e],
                              count_window=False)


#: entries (detections, or distinct (peak, step, code) keys) evaluated at once by
#: :func:`points_from_peak_detections`; sums are sequential in entry order, so the
#: blocks change no bit of the result
ENTRY_BLOCK = 1 << 15


def consistent_points(cloud: PointCloud, confidence: float = 0.997) -> PointCloud:
    """The points whose stereo and time-of-flight ranges agree within the bound.

    Two estimates of one surface must agree: a peak whose ranges differ by
    more than ``k·sqrt(σ_stereo² + σ_tof²)`` (attribute ``stereo_tof_z`` > k,
    k from ``confidence``) is not one surface — a false peak of background, or
    two surfaces inside one pixel — and is left out.
    """
    from mems_stereo.pipeline.consistency import k_from_confidence

    if "stereo_tof_z" not in cloud.attributes:
        return cloud
    return cloud.select(~(cloud["stereo_tof_z"] > k_from_confidence(confidence)))
