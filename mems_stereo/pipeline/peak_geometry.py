"""Per-peak stereo geometry the fusion needs: the inlier floor and the stereo
point at a peak's mean scan angle (with the pixel-location allowance).

Free functions of the system and the peaks' pixels (``rows``, ``cols`` (Q,)
int); metres, receiver camera frame.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.geometry.triangulation import epipolar_stereo_point
from mems_stereo.geometry.uncertainty import _rays, spreads_for, stereo_point_est

#: pixels either side of a peak's pixel whose stereo range span floors the inlier bound
#: (:func:`footprint_halfwidth`)
INLIER_FOOTPRINT_PX = 1.0
#: systematic uncertainty, in pixels, of where a peak's band puts the spot's centre
STEREO_PIXEL_SIGMA = 0.05


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
    x = centre[ok, None] * _rays(system, u, v)
    d = x - p
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = INLIER_FOOTPRINT_PX
    r = [np.linalg.norm(epipolar_stereo_point(p, d, _rays(system, u + a, v))[0], axis=1)
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


def stereo_at_mean_angle(system, rows, cols, theta_sum, n, mean: dict):
    """Stereo point of each peak at its detections' mean scan angle (in place).

    A detection's stereo range is a convex function of its angle (range ∝ 1 /
    disparity): the mean of the ranges over a band of angles lies behind the
    surface (by ≈ var(disparity)/disparity², a centimetre at 1 m for a
    strong return that fires the pixel over several pixel footprints), the
    range at the mean angle does not.  ``theta_sum``, ``n`` (Q,): the sum of the
    inliers' angles (rad) and their number; ``mean["stereo"]`` is replaced.
    Returns ``(C, range_per_px)``: the systematic covariance of the pixel
    location (:data:`STEREO_PIXEL_SIGMA`), ``{"stereo": C (Q, 3, 3)}``, to add
    unscaled, and the (Q, 3) m per pixel at the mean angle (for the depth
    edges); ``(None, None)`` when no peak has a mean angle.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        th = theta_sum / n
    ok = np.isfinite(th) & (n > 0)
    if not np.any(ok):
        return None, None
    x_old = mean["stereo"][0]
    x_new = x_old.copy()
    x_new[ok] = stereo_point_est(system, cols[ok].astype(np.float64),
                                 rows[ok].astype(np.float64), np.zeros(ok.sum()),
                                 th[ok])
    good = ok & np.all(np.isfinite(x_new), axis=1)
    x_new[~good] = x_old[~good]
    # the band locates the spot's centre on the pixel to a fraction of a pixel
    # (spot profile, band edges, a surface inclined across the footprint):
    # STEREO_PIXEL_SIGMA px along the row, propagated at the mean angle
    J = np.zeros_like(x_new)
    if np.any(good):
        u = cols[good].astype(np.float64)
        v = rows[good].astype(np.float64)
        z = np.zeros(u.size)
        J[good] = (stereo_point_est(system, u + 0.5, v, z, th[good])
                   - stereo_point_est(system, u - 0.5, v, z, th[good]))
    J = np.nan_to_num(J)
    C_sys = STEREO_PIXEL_SIGMA ** 2 * J[:, :, None] * J[:, None, :]
    mean["stereo"] = (x_new, mean["stereo"][1])
    return {"stereo": C_sys}, J
