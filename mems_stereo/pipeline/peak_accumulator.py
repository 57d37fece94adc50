"""The streaming fusion of each peak's signal detections into sums per peak
(:class:`PeakAccumulator`), and the per-entry points and ranges it sums
(:class:`EntryPoints`).  Units: metres, receiver camera frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.geometry.uncertainty import polar_from_cartesian
from mems_stereo.model.system import System
from mems_stereo.physics.first_photon import (
    MU_GRID,
    OUTLIER_PROBABILITY,
    detection_log_odds,
)
from mems_stereo.physics.first_photon_band_kernel import kernels as band_kernels
from mems_stereo.physics.first_photon_band_kernel import log_odds
from mems_stereo.physics.spot import spot_fraction
from mems_stereo.pipeline.classify_kernel import compiles
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.consistency import k_from_confidence
from mems_stereo.pipeline.detections import DetectionPoints, StereoCache, detection_points
from mems_stereo.pipeline.fusion_inputs import FusionOptions, FusionPeaks
from mems_stereo.pipeline.peak_estimates import peak_means_of
from mems_stereo.pipeline.peak_geometry import footprint_halfwidth
from mems_stereo.pipeline.peak_means import PeakMeans
from mems_stereo.pipeline.sums import PeakSums, RangeMode, add_rows_gathered


@dataclass(frozen=True, slots=True, eq=False)
class EntryPoints:
    """The fused range of each of M entries, for the mode and the inlier test, and
    (where computed) their points.

    peak : (M,) int64, the entry's peak.
    code : (M,) the entry's TDC code (float64 where the accumulator converted it).
    r : (M,) float64 m, the fused point's range.
    sigma_r : (M,) float64 m, its σ.
    ok : (M,) bool, a finite point with σ > 0.
    weight : (M,) float64 multiplicity, or None (not yet attached).
    points : the entries' :class:`~mems_stereo.pipeline.detections.DetectionPoints`,
        or None (fused ranges alone, :meth:`PeakAccumulator.fused_ranges`).
    """

    peak: np.ndarray
    code: np.ndarray
    r: np.ndarray
    sigma_r: np.ndarray
    ok: np.ndarray
    weight: np.ndarray | None = None
    points: DetectionPoints | None = None

    def with_weight(self, code, weight) -> EntryPoints:
        """These ranges with the entries' ``code`` and ``weight`` (M,) attached."""
        return replace(self, code=code, weight=weight)


def empty_band(Q: int):
    """``(step_lo, step_hi)`` (Q,) int64 each of no inlier yet (lo > hi)."""
    return (np.full(Q, np.iinfo(np.int64).max, np.int64), np.full(Q, -1, np.int64))


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

    First-photon correction of the time-of-flight estimate (``first_photon``, on by
    default; it needs ``shots_per_step`` and ``step_grid``, the valid shots per
    scan-angle step of the interval table's grid, and is skipped without them). A SPAD
    records the first photon of a shot, so a strong return arrives early (δ ≈ −0.6 ns at
    μ = 0.35 photons per shot, −1.8 ns at 1, −5.9 ns at 4 with the 14.9 ns pulse) and
    one at the TDC start late
    (:func:`~mems_stereo.physics.first_photon.first_photon_moments`). μ comes from which
    shots fired: a shot at angle θ puts the share ``f(θ)`` of the spot on the pixel
    (:func:`spot_fraction`, target at the peak's centre range) and fires with
    ``p = 1 − exp(−μ0·f)``. Each inlier adds its log-odds on a grid of μ0
    (:data:`~mems_stereo.physics.first_photon.MU_GRID`, :meth:`add_inliers`); at
    :meth:`cloud` the steps around the inliers' angle band add ``N_s·ln(1 − p_s)`` for
    every valid shot; the posterior of μ0 (uniform in log μ0) gives the expected delay
    of the detections' mean
    (:func:`~mems_stereo.physics.first_photon.first_photon_delay`). The spot profile
    carries the information a saturated detection rate (every shot fires) lacks: the
    stronger the return, the further outside the pixel the spot still fires it. The
    delay is removed from the ToF mean (the fused mean moves by its ToF share), a
    detection's timing variance becomes the first-photon one, and the posterior spread
    of the delay is added in quadrature (after the Birge scaling). Assumptions: the spot
    model (Gaussian, ``spot_sigma``; default the simulator's
    :class:`~mems_stereo.physics.spot.SpotModel` at the peak's range), the background
    inside the window subtracted
    (:func:`~mems_stereo.pipeline.window_background.window_background`), the target's
    range constant across the band, a Gaussian pulse of the system's ``pulse_fwhm`` ⊕
    the spreads' jitter.
    """

    def __init__(self, system: System, peaks: FusionPeaks,
                 options: FusionOptions | None = None):
        o = FusionOptions() if options is None else options
        self.system = system
        self.shots_per_step = (None if o.shots_per_step is None or o.step_grid is None
                               else np.asarray(o.shots_per_step, dtype=np.int64).ravel())
        self.step_grid = None if o.step_grid is None else (float(o.step_grid[0]),
                                                           float(o.step_grid[1]))
        self.first_photon = bool(o.first_photon)
        self.spot_sigma = None if o.spot_sigma is None else float(o.spot_sigma)
        self.spreads = o.spreads
        self.k = k_from_confidence(o.confidence)
        self.rows = np.asarray(peaks.rows, dtype=np.int64).ravel()
        self.cols = np.asarray(peaks.cols, dtype=np.int64).ravel()
        if self.rows.shape != self.cols.shape:
            raise GeometryError("rows, cols: expected equal lengths")
        self.peak_code = None if peaks.code is None else np.asarray(peaks.code, np.float64)
        self.Q = self.rows.size
        # (step_lo, step_hi) (Q,) each: the steps pass 2 counted; accept(steps (Q, B),
        # centre (Q,)) -> (Q, B) bool: steps where the return's code is classified signal
        self.step_window = peaks.step_window
        self.accept = peaks.accept
        self.turning = (np.zeros(self.Q, bool) if peaks.turning is None
                        else np.asarray(peaks.turning, bool).ravel())
        self.rate_hz = (np.zeros(self.Q) if peaks.rate_hz is None
                        else np.nan_to_num(np.asarray(peaks.rate_hz, np.float64).ravel()))
        self.mode = RangeMode(self.Q, o.r_min, o.r_max, o.rel_step)
        self.centre = None
        Q = self.Q
        self.sums = PeakSums.zeros(Q)
        self.band = empty_band(Q)  # inliers' angle steps: min, max (merged, not summed)
        self._stereo: StereoCache | None = None

    def empty_copy(self) -> PeakAccumulator:
        """A zeroed accumulator of the same peaks and grid (keeps the centres)."""
        new = object.__new__(PeakAccumulator)
        new.__dict__.update(self.__dict__)
        new.mode = self.mode.zeroed()
        new.sums = PeakSums.zeros(self.Q)
        new.band = empty_band(self.Q)
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

    def points_of(self, shot, peak, code, theta) -> DetectionPoints:
        """The :class:`DetectionPoints` of entries (M,) of peaks ``peak`` at
        ``theta[shot]``, with the accumulator's stereo geometry cache."""
        return detection_points(self.system, shot, self.rows[peak], self.cols[peak], code,
                                theta, self.spreads, stereo_cache=self.stereo_cache())

    def entry_points(self, shot, peak, code, theta, weight=None) -> EntryPoints:
        """The entries' points and fused ranges (arguments as :meth:`add_mode`)."""
        shot = np.asarray(shot, dtype=np.int64).ravel()
        peak = np.asarray(peak, dtype=np.int64).ravel()
        code = np.asarray(code, dtype=np.float64).ravel()
        w = (np.ones(shot.shape) if weight is None
             else np.asarray(weight, dtype=np.float64).ravel())
        if not (shot.shape == peak.shape == code.shape == w.shape):
            raise GeometryError("shot, peak, code, weight: expected equal lengths")
        dp = self.points_of(shot, peak, code, theta)
        pol = polar_from_cartesian(dp.fused, dp.cov_fused)
        r, sr = pol.r, pol.sigma_r
        ok = dp.ok & np.isfinite(r) & np.isfinite(sr) & (sr > 0)
        return EntryPoints(peak, code, r, sr, ok, w, dp)

    def stereo_cache(self) -> StereoCache:
        """The stereo geometry of the (pixel, step) runs this accumulator has evaluated
        (its sub-passes and inlier margins meet each several times)."""
        if self._stereo is None:
            self._stereo = StereoCache()
        return self._stereo

    def release_stereo_cache(self) -> None:
        """Drop the stereo geometry cache (the sub-passes are done with it)."""
        self._stereo = None

    def fused_ranges(self, peak, code, theta) -> EntryPoints:
        """The ranges of :meth:`entry_points` for entries at angles ``theta`` (M,) (the
        same bits), from the fused points alone (no stereo or ToF covariances; no
        weight and no points attached)."""
        peak = np.asarray(peak, dtype=np.int64).ravel()
        code = np.asarray(code, dtype=np.float64).ravel()
        x, C, ok = detection_points(self.system, np.arange(peak.size), self.rows[peak],
                                    self.cols[peak], code, theta, self.spreads,
                                    fused_only=True, stereo_cache=self.stereo_cache())
        # r and σ_r as polar_from_cartesian computes them
        r = np.linalg.norm(x, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            gr = x / r[:, None]
        sr = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", gr, C, gr), 0.0))
        ok = ok & np.isfinite(r) & np.isfinite(sr) & (sr > 0)
        return EntryPoints(peak, code, r, sr, ok)

    def add_mode(self, shot, peak, code, theta, weight=None) -> None:
        """Sub-pass 1: coverage of each detection's ±σ range interval.

        ``shot, peak, code`` (M,) int; ``theta`` (K,) rad indexed by ``shot``;
        ``weight`` (M,) multiplicities (default 1): identical detections
        counted once with their number, possibly scaled by their probability
        of being signal.
        """
        self.add_mode_entries(self.entry_points(shot, peak, code, theta, weight))

    def add_mode_entries(self, e: EntryPoints) -> None:
        """Sub-pass 1 over entries whose fused ranges and weights are known."""
        ok = e.ok
        self.mode.add(e.peak[ok], e.r[ok], e.sigma_r[ok], e.weight[ok])

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
        self.add_inlier_entries(self.entry_points(shot, peak, code, theta, weight), shot,
                                theta, background)

    def add_inlier_entries(self, e: EntryPoints, shot, theta, background=None,
                           inlier_points: Callable | None = None, may_be_inlier=None,
                           count_window: bool = True) -> None:
        """The sums of :meth:`add_inliers` from the entries' fused ranges ``e`` (with
        their weights); ``inlier_points(inl)`` gives the :class:`DetectionPoints` of
        the inliers only (default: ``e.points`` of them; each entry's points are its
        own, so computing them for the inliers alone changes no bit).  Every per-peak
        sum is sequential in entry order (``np.add.at``), so adding the entries in
        blocks gives the sums of adding them at once, bit for bit.
        ``may_be_inlier`` (M,) bool or None: entries allowed in the inlier sums;
        ``count_window``: whether the entries count in the window (and the
        first-photon likelihood)."""
        s = self.sums
        peak, code, r, sr, ok, m = e.peak, e.code, e.r, e.sigma_r, e.ok, e.weight
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
        dp = e.points.subset(inl) if inlier_points is None else inlier_points(inl)
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
            self._add_band_and_likelihood(peak, shot, theta, inl, m_all)
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
            # is that of the mean angle (see :func:`peak_means_of`)
            np.add.at(s.b1, q, b * th_e)
            np.add.at(s.b2, q, b * th_e ** 2)
            r_tof = np.linalg.norm(dp.tof, axis=1)
            np.add.at(s.bt1, q, b * r_tof)
            np.add.at(s.bt2, q, b * r_tof ** 2)

    def _add_band_and_likelihood(self, peak, shot, theta, inl, m_all) -> None:
        """The inliers' angle band, and every window entry's first-photon log-odds.

        Band: the inliers' steps; likelihood: every detection of the window (the
        in-peak test drops true returns at the band's edges, where the spot is half
        off the pixel: counting those shots as misses would bias μ0 low)."""
        q = peak[inl]
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
        kern = band_kernels() if compiles(0, 1) else None  # (a frame's passes)
        odds = (detection_log_odds(f) if kern is None
                else log_odds(kern[2], f, MU_GRID, OUTLIER_PROBABILITY))
        add_rows_gathered(self.sums.loglik, peak, odds, run, m_all)

    def cloud(self, min_counts: int = 1, own=None) -> PointCloud:
        """One point per peak with at least ``min_counts`` inliers (see class docstring).

        ``own`` : (a, b) or None — points of peaks a..b−1 only; the others are the
        block's halo, fused so that the depth edges of its own peaks see every
        neighbour (:func:`mems_stereo.pipeline.block_fusion.points_block`)."""
        return self.peak_means().cloud(min_counts, own)

    def peak_means(self) -> PeakMeans:
        """Each peak's stereo and ToF means with every term of their σ
        (:func:`~mems_stereo.pipeline.peak_estimates.peak_means_of`)."""
        return peak_means_of(self)
