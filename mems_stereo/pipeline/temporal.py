"""Temporal fusion of frames: each pixel's points merged over frames while they agree.

A pixel sees at most one point per frame (one peak per pixel, with its scan-angle band:
the interval table's steps ``step_lo..step_hi`` its pass 2 counted).  For every pixel
:class:`TemporalFusion` keeps the inverse-variance sums of the points it has fused since
its last restart.  A new point of the pixel *agrees* with that history when

* its band overlaps the history's last band (the beam meets the pixel's ray at the same
  scan angles, i.e. the same spot of the surface), and
* its range and the history's fused range differ by at most
  ``k·sqrt(σ_r² + σ_acc²)`` — the pipeline's own consistency test (the stereo/ToF test
  of :func:`~mems_stereo.pipeline.fusion.consistent_points`, the classifier's bound),
  k = Φ⁻¹((1 + confidence)/2) (2.97 at the default 0.997).

An agreeing point is added (weights w = 1/σ_r²: the fused range and position are the
w-weighted means, the other σ propagated through the fixed weights,
``sqrt(Σ w² σ²)/Σw``, each σ times the history's Birge ratio where its frames scatter
more than their σ say, as the pipeline scales a peak's σ by its detections' reduced χ²);
one that does not agree restarts the pixel's history with itself.

**σ model.**  A frame point's error is a random part (photon counts, timing, pixel
extent: the pipeline's σ_r, independent from frame to frame) plus a part common to every
frame of the pixel, σ_sys (``systematic(cloud)``, by default :func:`shared_errors`: what
a frame's removal of its mean-angle bias leaves of the scan's dwell skew
(:class:`~mems_stereo.pipeline.scan_dwell.DwellSkew`), the first-photon
model's share of the time of flight, :func:`tof_model_share`, and a calibrated system's
parameter errors).  Only the random part averages:

    σ_r,fused² = B²/Σw + (Σ w·σ_sys / Σw)²         (B the Birge ratio)

(the common parts are fully correlated, so they add linearly through the weights), and
σ_x, σ_y, σ_z likewise with the common displacement's components.  The agreement test
compares a frame with its own history: the common part cancels in ``r − r̄``, so the
test uses the random σ alone.  A fused point of age 1 carries its frame's σ_r and σ_sys.
Nothing is forgotten otherwise: a static surface sharpens as 1/√age down to its σ_sys, a
moving one restarts as soon as it has moved by about kσ.  Under the Gaussian errors the
bound assumes, a static pixel's first false restart comes with probability 1 − confidence
per frame; a restart starts from the outlier that failed, so more follow (measured:
docs/frames.md).
"""

from __future__ import annotations

import numpy as np

from mems_stereo.geometry.uncertainty import spreads_for
from mems_stereo.physics.first_photon import first_photon_timing
from mems_stereo.pipeline.calibration_sigma import (
    calibration_covariance,
    calibration_point_covariance,
)
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.consistency import k_from_confidence
from mems_stereo.pipeline.first_photon_correction import MODEL_DELAY_FRACTION, MU_MODEL_FACTOR
from mems_stereo.pipeline.peak_geometry import ANGLE_BIAS_FRACTION
from mems_stereo.pipeline.scan_dwell import DwellSkew, Systematic

#: the attributes the fusion replaces by their fused values (besides points)
FUSED_SIGMAS = ("sigma_x", "sigma_y", "sigma_z", "sigma_phi")


class TemporalFusion:
    """Per-pixel history of fused points of a ``height`` × ``width`` receiver (pixel
    ``row·width + col``).

    :meth:`update` takes a frame's cloud (attributes ``row``, ``pixel``, ``range``,
    ``sigma_r``, ``counts``, ``t``, ``step_lo``, ``step_hi`` and the σ of
    :data:`FUSED_SIGMAS` where present) and returns it fused with each pixel's history:
    points, ``range``, ``sigma_r``, the σ, ``counts`` (summed) and ``t`` (count-weighted
    mean) replaced, ``age`` (int32, frames fused) added; the other attributes stay the
    frame's.  ``tests`` and ``restarts`` count the points that met a history and those
    of them that did not agree with it.

    ``system`` : the :class:`~mems_stereo.model.system.System` (a line scanner: the
    default ``systematic`` is :func:`shared_errors`: its dwell skew, the first-photon
    model's share and its calibration's share);
    ``systematic`` : a callable ``cloud -> Systematic`` (σ_sys (N,) m and the common
    displacement (N, 3) m of each point), or None for none (random errors only).
    """

    def __init__(self, height: int, width: int, confidence: float = 0.997, system=None,
                 systematic=None):
        self.k = k_from_confidence(confidence)
        line = system is not None and getattr(system.scanner, "axis2", None) is None
        if systematic is None and line:
            systematic = shared_errors(system)
        self.systematic = systematic
        self.width = int(width)
        P = int(height) * self.width
        self.age = np.zeros(P, np.int32)
        self.wsum = np.zeros(P)
        self.wx = np.zeros((P, 3))
        self.wr = np.zeros(P)
        self.wr2 = np.zeros(P)
        self.w2s = np.zeros((P, len(FUSED_SIGMAS)))
        self.wsys = np.zeros(P)
        self.wdx = np.zeros((P, 3))
        self.csum = np.zeros(P)
        self.ct = np.zeros(P)
        self.band = np.zeros((P, 2), np.int64)
        self.tests = 0
        self.restarts = 0

    def agrees(self, pix: np.ndarray, r: np.ndarray, sigma_r: np.ndarray,
               band: np.ndarray) -> np.ndarray:
        """(N,) bool: which points agree with their pixel's history (none without one)."""
        has = self.age[pix] > 0
        ws = np.where(has, self.wsum[pix], 1.0)
        r_acc = self.wr[pix] / ws
        with np.errstate(invalid="ignore"):
            z = np.abs(r - r_acc) / np.sqrt(sigma_r ** 2 + 1.0 / ws)
        overlap = (band[:, 0] <= self.band[pix, 1]) & (band[:, 1] >= self.band[pix, 0])
        return has & overlap & (z <= self.k)

    def update(self, cloud: PointCloud) -> PointCloud:
        """The frame's cloud fused with each pixel's history (see the class)."""
        a = cloud.attributes
        n = len(cloud)
        pix = pixel_index(cloud, self.width)
        s_r = np.asarray(a["sigma_r"], np.float64)
        ok = np.isfinite(s_r) & (s_r > 0) & np.all(np.isfinite(cloud.points), axis=1)
        band = np.stack([a["step_lo"], a["step_hi"]], axis=1).astype(np.int64) if n \
            else np.zeros((0, 2), np.int64)
        agree = self.agrees(pix, a["range"], s_r, band) & ok
        had = (self.age[pix] > 0) & ok
        self.tests += int(had.sum())
        self.restarts += int((had & ~agree).sum())
        self._reset(pix[~agree])
        p, sel = pix[ok], ok
        w = 1.0 / s_r[sel] ** 2
        self.age[p] += 1
        self.wsum[p] += w
        self.wx[p] += w[:, None] * cloud.points[sel]
        self.wr[p] += w * a["range"][sel]
        self.wr2[p] += w * a["range"][sel] ** 2
        sig = np.stack([np.asarray(a.get(k, np.zeros(n)), np.float64) for k in FUSED_SIGMAS],
                       axis=1)
        self.w2s[p] += (w[:, None] * sig[sel]) ** 2
        if self.systematic is not None:
            common = self.systematic(cloud.select(sel))
            self.wsys[p] += w * common.sigma_r
            self.wdx[p] += w[:, None] * common.dx
        c = np.asarray(a["counts"], np.float64)[sel]
        self.csum[p] += c
        self.ct[p] += c * np.asarray(a["t"], np.float64)[sel]
        self.band[p] = band[sel]
        return self._fused(cloud, pix, ok)

    def scatter_ratio(self, pix: np.ndarray) -> np.ndarray:
        """(n,) Birge ratio of each pixel's history: sqrt of its reduced χ² of the ranges
        about their weighted mean, ``Σw(r − r̄)²/(age − 1)``, where it exceeds 1, else 1
        (1 for a history of one frame)."""
        ws = self.wsum[pix]
        chi2 = np.maximum(self.wr2[pix] - self.wr[pix] ** 2 / ws, 0.0)
        dof = np.maximum(self.age[pix] - 1, 1)
        return np.sqrt(np.maximum(chi2 / dof, 1.0))

    def _reset(self, pix: np.ndarray) -> None:
        for arr in (self.age, self.wsum, self.wx, self.wr, self.wr2, self.w2s, self.csum,
                    self.ct, self.wsys, self.wdx):
            arr[pix] = 0

    def _fused(self, cloud: PointCloud, pix: np.ndarray, ok: np.ndarray) -> PointCloud:
        """The cloud with its points' fused values (points not ``ok`` stay as they are,
        age 1)."""
        a = dict(cloud.attributes)
        pts = cloud.points.copy()
        p = pix[ok]
        ws = self.wsum[p]
        birge = self.scatter_ratio(p)
        pts[ok] = self.wx[p] / ws[:, None]
        s_r = np.hypot(birge / np.sqrt(ws), self.wsys[p] / ws)
        for name, vals in (("range", self.wr[p] / ws), ("sigma_r", s_r),
                           ("t", self.ct[p] / np.maximum(self.csum[p], 1e-300))):
            v = np.array(a[name], np.float64)
            v[ok] = vals
            a[name] = v
        for j, name in enumerate(FUSED_SIGMAS):
            if name in a:
                v = np.array(a[name], np.float64)
                v[ok] = birge * np.sqrt(self.w2s[p, j]) / ws
                if j < 3:  # sigma_x, y, z: the common displacement's component
                    v[ok] = np.hypot(v[ok], self.wdx[p, j] / ws)
                a[name] = v
        counts = np.array(a["counts"])
        counts[ok] = np.rint(self.csum[p]).astype(counts.dtype)
        a["counts"] = counts
        age = np.ones(len(cloud), np.int32)
        age[ok] = self.age[p]
        a["age"] = age
        return PointCloud(pts, a)


def shared_errors(system):
    """``cloud -> Systematic``: the errors every frame of a pixel shares on a line
    scanner, the scan's dwell skew (:class:`~mems_stereo.pipeline.scan_dwell.DwellSkew`)
    as far as its removal leaves it (a frame removes every peak's expected mean-angle
    bias, :mod:`~mems_stereo.pipeline.frame_bias`, within
    :data:`~mems_stereo.pipeline.peak_geometry.ANGLE_BIAS_FRACTION` of it), the
    first-photon model's share of the time of flight (:func:`tof_model_share`) and,
    for a system that carries its calibration's covariance, the calibration's share
    of each point (:func:`~mems_stereo.pipeline.calibration_sigma.calibration_point_covariance`:
    a parameter error moves every frame's point alike, so it must not average down with
    the frames); they are independent and add in quadrature."""
    skew = DwellSkew(system).systematic
    tof = tof_model_share(system)
    with_cal = calibration_covariance(system) is not None

    def dwell(cloud: PointCloud) -> Systematic:
        d = skew(cloud)  # removed in every frame, but for its allowance
        return Systematic(ANGLE_BIAS_FRACTION * d.sigma_r, ANGLE_BIAS_FRACTION * d.dx)

    def systematic(cloud: PointCloud) -> Systematic:
        common = _plus(dwell(cloud), tof(cloud))
        if not with_cal or len(cloud) == 0:
            return common
        n = len(cloud)
        a = cloud.attributes
        x = np.asarray(cloud.points, np.float64)
        rows = np.asarray(a["row"]) if "row" in a else np.zeros(n, np.int64)
        w = (np.nan_to_num(np.asarray(a["weight_stereo"], np.float64), nan=1.0)
             if "weight_stereo" in a else np.ones(n))
        cov = calibration_point_covariance(system, x, rows, np.asarray(a["pixel"]), w,
                                           np.asarray(a["counts"], np.float64))
        var_r = np.maximum(np.einsum("qi,qij,qj->q", _unit(x), cov, _unit(x)), 0.0)
        sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
        return _plus(common, Systematic(np.sqrt(var_r), sd))

    return systematic


def tof_model_share(system):
    """``cloud -> Systematic``: the part of each point's time of flight that the
    first-photon model fixes alike in every frame of a pixel.

    The correction removes a delay d (``tof_delay``, s; NaN: none) computed from the
    spot model's signal level μ0 (``signal_photons``); the model's allowance for its own
    error — :data:`~mems_stereo.pipeline.first_photon_correction.MODEL_DELAY_FRACTION`
    of d, and half the delay's change between μ0/F and μ0·F
    (F = :data:`~mems_stereo.pipeline.first_photon_correction.MU_MODEL_FACTOR`, the
    spot model misjudging the level) — is in each frame's σ but is the same misjudgement
    in every frame of a static pixel, so it does not average.  The change is taken
    from the single-return model (:func:`~mems_stereo.physics.first_photon.first_photon_timing`)
    relative to its delay at μ0, times d; as range ``c·|d|/2``, weighted by the time of
    flight's share of the fused point (``1 − weight_stereo``), along the point's ray.
    Where the stereo carries the point (most pixels) it is nearly 0; where it is the
    time of flight alone (a turning peak whose angle is not solved, ``Peaks.turning``:
    a pixel the spot's tail alone lights) it is most of the frame's range σ that the
    frames' averaging must keep."""
    sp = spreads_for(system)
    sigma = float(np.hypot(sp.sigma_t_pulse, sp.sigma_t_jitter))
    c = system.speed_of_light
    F = MU_MODEL_FACTOR

    def share(cloud: PointCloud) -> Systematic:
        n = len(cloud)
        a = cloud.attributes
        if n == 0 or "tof_delay" not in a or "signal_photons" not in a or sigma <= 0:
            return Systematic(np.zeros(n), np.zeros((n, 3)))
        d = np.abs(np.nan_to_num(np.asarray(a["tof_delay"], np.float64)))
        mu = np.nan_to_num(np.asarray(a["signal_photons"], np.float64))
        w_tof = 1.0 - np.clip(np.nan_to_num(np.asarray(
            a.get("weight_stereo", np.ones(n)), np.float64), nan=1.0), 0.0, 1.0)
        on = (w_tof > 0) & (mu > 0) & (d > 0)
        far = np.full(int(on.sum()), 50.0 * sigma)  # far from the TDC start: no truncation
        with np.errstate(invalid="ignore", divide="ignore"):
            delay = [np.abs(first_photon_timing(far, m, sigma)[1]) for m in
                     (mu[on], mu[on] * F, mu[on] / F)]
            rel = np.nan_to_num(0.5 * np.abs(delay[1] - delay[2]) / delay[0])
        s_r = np.zeros(n)
        s_r[on] = w_tof[on] * 0.5 * c * d[on] * np.hypot(MODEL_DELAY_FRACTION, rel)
        return Systematic(s_r, s_r[:, None] * np.abs(_unit(cloud.points)))

    return share


def _plus(a: Systematic, b: Systematic) -> Systematic:
    """Two independent common parts in quadrature."""
    return Systematic(np.hypot(a.sigma_r, b.sigma_r), np.hypot(a.dx, b.dx))


def _unit(x) -> np.ndarray:
    """(N, 3) unit vectors of the points ``x`` (0 where undefined)."""
    x = np.asarray(x, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.nan_to_num(x / np.linalg.norm(x, axis=1, keepdims=True))


def pixel_index(cloud: PointCloud, width: int) -> np.ndarray:
    """(N,) int64 flat pixel ``row·width + pixel`` of each point (row 0 where the cloud
    has no ``row``)."""
    col = np.asarray(cloud["pixel"], np.int64)
    if "row" not in cloud.attributes:
        return col
    return np.asarray(cloud["row"], np.int64) * int(width) + col
