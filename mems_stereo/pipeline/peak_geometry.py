"""Per-peak stereo geometry the fusion needs: the inlier floor and the stereo
point at a peak's mean scan angle (less its expected bias), with its covariance.

Free functions of the system and the peaks' pixels (``rows``, ``cols`` (Q,)
int); metres, receiver camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.geometry.triangulation import epipolar_stereo_point
from mems_stereo.geometry.uncertainty import pixel_rays, propagate, spreads_for, stereo_point_est

#: pixels either side of a peak's pixel whose stereo range span floors the inlier bound
#: (:func:`footprint_halfwidth`)
INLIER_FOOTPRINT_PX = 1.0
#: relative systematic uncertainty of the mean-angle bias the fusion removes
#: (:func:`~mems_stereo.pipeline.first_photon_correction.mean_angle_bias`): the share
#: of the predicted bias left as stereo error after the correction, as measured on the
#: scenario sweep
ANGLE_BIAS_FRACTION = 0.2
#: rad, the angle step of the central difference ∂x/∂θ of the stereo point
_DTHETA = 1e-5


def footprint_halfwidth(system, rows, cols, centre, spreads=None) -> np.ndarray:
    """(Q,) m: half the stereo range span of ±:data:`INLIER_FOOTPRINT_PX` pixels about
    each peak's pixel at its centre range (0 where undefined); ``rows``, ``cols``,
    ``centre`` (Q,) the peaks' pixels and centre ranges (m), ``spreads`` as the
    fusion's (default :func:`spreads_for`).

    A return fires the pixel while the spot crosses its footprint and, when
    strong or defocused (near range), while the spot's tails are still on
    it: its detections' stereo ranges spread over that span, several of one
    detection's σ.  With few detections the mode's plateau cannot show it
    and the inlier bound would cut true returns; the angle band of pass 2
    has already selected the steps, so this floor lets the band's
    detections in (their mean is taken at the mean angle: no bias).
    """
    out = np.zeros(np.asarray(rows).size)
    ok = np.isfinite(centre) & (centre > 0)
    if not np.any(ok):
        return out
    u = cols[ok].astype(np.float64)
    v = rows[ok].astype(np.float64)
    p = np.asarray(system.scanner.position, dtype=np.float64)
    x = centre[ok, None] * pixel_rays(system, u, v)
    d = x - p
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = INLIER_FOOTPRINT_PX
    r = [np.linalg.norm(epipolar_stereo_point(p, d, pixel_rays(system, u + a, v)).points, axis=1)
         for a in (-h, h)]
    span = np.nan_to_num(0.5 * np.abs(r[1] - r[0]), nan=0.0, posinf=0.0)
    # the inlier test is on the fused range: the stereo spread enters it by the
    # stereo's weight (far, or with a short baseline, the ToF decides alone and the
    # floor must not open the bound to the whole window)
    sp = spreads_for(system) if spreads is None else spreads
    var_st = (sp.sigma_u * span / h) ** 2
    var_tof = (0.5 * sp.sigma_L(system)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(var_st + var_tof > 0, var_tof / (var_st + var_tof), 0.0)
    out[ok] = w * span
    return out


@dataclass(frozen=True, slots=True)
class MeanAngleStereo:
    """The stereo point of Q peaks at their mean scan angle (:func:`stereo_at_mean_angle`).

    point : (Q, 3) float64 m, the point at the mean angle (the given point where
        there is none).
    cov_sys : (Q, 3, 3) float64 m², its systematic covariance (the angle grid's
        quantisation, the bias correction's allowance), to add unscaled; None when
        no peak has a mean angle.
    range_per_px : (Q, 3) float64 m per pixel at the mean angle (for the depth
        edges); None when no peak has a mean angle.
    """

    point: np.ndarray
    cov_sys: np.ndarray | None
    range_per_px: np.ndarray | None


def stereo_at_mean_angle(system, rows, cols, theta_sum, n, point, angle_bias=None,
                         step=None, removed=None) -> MeanAngleStereo:
    """Stereo point of each peak at its detections' mean scan angle.

    A detection's stereo range is a convex function of its angle (range ∝ 1 /
    disparity): the mean of the ranges over a band of angles lies behind the
    surface (by ≈ var(disparity)/disparity², a centimetre at 1 m for a
    strong return that fires the pixel over several pixel footprints), the
    range at the mean angle does not.  ``theta_sum``, ``n`` (Q,): the sum of the
    inliers' angles (rad) and their number; ``point`` (Q, 3) m the stereo point it
    replaces (kept where there is no mean angle).
    ``angle_bias`` (Q,) rad or None: the mean angle's expected bias
    (:func:`~mems_stereo.pipeline.first_photon_correction.mean_angle_bias`),
    removed from it where ``removed`` (Q,) bool (default everywhere), with
    :data:`ANGLE_BIAS_FRACTION` of it as systematic σ; where not removed, all
    of it is.
    ``step`` (rad) or None: the angle grid the detections were placed on (each
    at its step's angle): the mean angle is known to within that grid, a
    systematic σ of ``step / √12`` (uniform over one step; 0.006 px of the
    footprint for the paper's system).
    Returns the point, these systematic covariances and the metres per pixel at the
    mean angle (:class:`MeanAngleStereo`).
    """
    bias = (np.zeros(np.asarray(n).shape) if angle_bias is None
            else np.nan_to_num(np.asarray(angle_bias, np.float64)))
    rm = np.ones(bias.shape, bool) if removed is None else np.asarray(removed, bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        th = theta_sum / n - np.where(rm, bias, 0.0)
    ok = np.isfinite(th) & (n > 0)
    if not np.any(ok):
        return MeanAngleStereo(point, None, None)
    x_old = point
    x_new = x_old.copy()
    u = cols[ok].astype(np.float64)
    v = rows[ok].astype(np.float64)
    t = th[ok]
    # the point, ±½ px and ±½ dθ at once (each row its own: the same bits)
    x0, xu1, xu0, xt1, xt0 = stereo_points(system, [(u, v, t), (u + 0.5, v, t),
                                                    (u - 0.5, v, t), (u, v, t + 0.5 * _DTHETA),
                                                    (u, v, t - 0.5 * _DTHETA)])
    x_new[ok] = x0
    good = ok & np.all(np.isfinite(x_new), axis=1)
    x_new[~good] = x_old[~good]
    J = np.zeros_like(x_new)
    Jt = np.zeros_like(x_new)  # m per rad of the mean angle
    if np.any(good):
        g = good[ok]
        J[good] = xu1[g] - xu0[g]
        Jt[good] = np.nan_to_num((xt1[g] - xt0[g]) / _DTHETA)  # (stereo_angle_jacobian)
    J = np.nan_to_num(J)
    # the grid's quantisation and the bias correction's allowance, along ∂x/∂θ
    var_th = ((0.0 if step is None else float(step) ** 2 / 12.0)
              + (np.where(rm, ANGLE_BIAS_FRACTION, 1.0) * bias) ** 2)
    C_sys = var_th[:, None, None] * Jt[:, :, None] * Jt[:, None, :]
    return MeanAngleStereo(x_new, C_sys, J)


def stereo_cov_at_mean_angle(system, rows, cols, theta_sum, n, count, spreads=None):
    """(Q, 3, 3) m²: the covariance of each peak's stereo at its mean angle, from
    ``count`` (Q,) independent detections (and subtracted background entries)
    over its ``n`` (Q,) net detections: one detection's stereo covariance at the
    mean angle (:func:`~mems_stereo.geometry.uncertainty.propagate`) times
    ``count / n²``.  NaN where a peak has no mean angle.

    The stereo of the peak is the point at the mean angle
    (:func:`stereo_at_mean_angle`), so its spread is the mean angle's,
    propagated at that angle.  The mean of the detections' own covariances
    (the form of a mean of their points) weighs each at its own angle: range
    is convex in the angle (∝ 1 / disparity), and where the disparity is a few
    pixels (far, short baseline) the detections on the far side of the
    footprint, at twice the range and 16 times the variance, dominated it and
    overstated σ_stereo many times over.
    """
    rows = np.asarray(rows)
    out = np.full((rows.size, 3, 3), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        th = theta_sum / n
        k = count / (n * n)
    ok = np.isfinite(th) & np.isfinite(k) & (n > 0)
    if not np.any(ok):
        return out
    sp = spreads_for(system) if spreads is None else spreads
    z = np.zeros(int(ok.sum()))
    _, C = propagate(stereo_point_est, system, cols[ok].astype(np.float64),
                     rows[ok].astype(np.float64), z, th[ok], sp, row_local=True)
    out[ok] = C * k[ok, None, None]
    return out


def stereo_angle_jacobian(system, rows, cols, theta) -> np.ndarray:
    """(Q, 3) m/rad: ∂x/∂θ of the stereo point of each peak's pixel at ``theta``
    (Q,) rad (central difference; 0 where undefined)."""
    out = np.zeros((np.asarray(rows).size, 3))
    ok = np.isfinite(theta)
    if np.any(ok):
        u = cols[ok].astype(np.float64)
        v = rows[ok].astype(np.float64)
        h = 0.5 * _DTHETA
        x1, x0 = stereo_points(system, [(u, v, theta[ok] + h), (u, v, theta[ok] - h)])
        out[ok] = (x1 - x0) / _DTHETA
    return np.nan_to_num(out)


def stereo_points(system, parts) -> list[np.ndarray]:
    """:func:`~mems_stereo.geometry.uncertainty.stereo_point_est` of each ``(u, v, θ)``
    of ``parts`` ((N_i,) float64 px, px, rad each), (N_i, 3) m each, in one evaluation
    on the parts laid end to end: every row is computed from its own inputs, so the
    same bits as one call per part."""
    sizes = [np.size(p[0]) for p in parts]
    u, v, th = (np.concatenate([np.asarray(p[i], np.float64).ravel() for p in parts])
                for i in range(3))
    x = stereo_point_est(system, u, v, np.zeros(u.size), th)
    return np.split(x, np.cumsum(sizes)[:-1])
