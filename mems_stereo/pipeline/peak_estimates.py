"""Each peak's stereo and time-of-flight means with every term of their σ, from the
sums of :class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator`.

The means weighted by multiplicity, scaled by the inliers' reduced χ² (Birge
ratio); the stereo taken at the mean scan angle less its expected bias; the
first-photon delay removed from the time of flight; the subtracted background's
Poisson fluctuation and the first-photon model's spread added.  Units: metres,
receiver camera frame.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.pipeline.first_photon_correction import correcting, first_photon_correction
from mems_stereo.pipeline.frame_bias import removing_every_bias
from mems_stereo.pipeline.peak_geometry import (
    stereo_angle_jacobian,
    stereo_at_mean_angle,
    stereo_cov_at_mean_angle,
)
from mems_stereo.pipeline.peak_means import PeakMeans, fuse_along_ray
from mems_stereo.pipeline.turning_angle import turning_angles

#: systematic σ, in pixels, of the stereo of a peak where the scan turns inside the
#: pixel's footprint and its angle is not solved (:func:`_with_turning`; mostly a pixel
#: the spot's tail alone lights, whose stereo at the mean angle less its expected bias
#: was 0.85 px off at the wall of benchmarks/bench_moving.py, seed 6, column 191)
TURNING_PIXEL_SIGMA = 1.0


def peak_means_of(acc) -> PeakMeans:
    """Each peak's stereo and ToF means of the accumulator ``acc`` (a
    :class:`~mems_stereo.pipeline.peak_accumulator.PeakAccumulator` after both
    sub-passes) with every term of their σ (scatter, pixel location, background,
    first-photon model): all of its cloud that is the peak's own (the first-photon
    step by blocks of :data:`~mems_stereo.pipeline.first_photon_correction.FP_BLOCK`
    peaks by index); the depth edges, which look at the row neighbours, are
    :meth:`PeakMeans.cloud`'s.  The means of blocks of peaks cut at multiples of
    ``FP_BLOCK``, joined (:meth:`PeakMeans.concat`), are the whole's."""
    s = acc.sums
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
    grid = None if acc.step_grid is None else acc.step_grid[1]
    st, mean["stereo"] = _stereo_at_mean_angle(acc, n, mean["stereo"], grid)
    # the first-photon correction needs the pulse's centre: from the peak-level
    # fusion of the stereo (at the mean angle) and uncorrected ToF means
    mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])[:2]
    fp = (first_photon_correction(acc, mean["fused"][0], mean["tof"]) if correcting(acc)
          else None)
    with np.errstate(invalid="ignore", divide="ignore"):  # ∂x/∂θ at the mean angle
        Jt = stereo_angle_jacobian(acc.system, acc.rows, acc.cols, s.theta / n)
    turn = None
    if fp is not None:  # the stereo at the mean angle less its expected bias
        mean["tof"] = fp.tof
        st, mean["stereo"], turn = _stereo_less_bias(acc, fp, Jt, mean["stereo"], birge,
                                                     grid)
    # the stereo mean's spread is that of its mean scan angle: binomial, not
    # Poisson, where the scan revisits its angles (angle_binomial_factor; a solved
    # turning peak's is binomial already)
    scale = {"stereo": birge if fp is None else
             birge * np.where(turn.solved, 1.0, fp.angle_binomial), "tof": birge}
    for name in ("stereo", "tof"):
        mean[name] = (mean[name][0], mean[name][1] * scale[name][:, None, None])
    if st.cov_sys is not None:  # systematic: not scaled
        mean["stereo"] = (mean["stereo"][0], mean["stereo"][1] + st.cov_sys)
    mean["stereo"] = _with_angle_background(acc, n, W, Jt, mean["stereo"])
    # the same for the time of flight: far away (stereo of no weight) a peak under
    # strong background is its ToF, and the background's Poisson fluctuation
    # across the accepted code interval (metres of range) is most of its error
    add_t = np.nan_to_num(var_bg_t)[:, None, None] * u_t[:, :, None] * u_t[:, None, :]
    mean["tof"] = (mean["tof"][0], mean["tof"][1] + np.nan_to_num(add_t))
    if fp is not None:  # the delay's posterior spread: systematic, not scaled
        D = s.tof.dL()[0]
        mean["tof"] = (mean["tof"][0], mean["tof"][1] + D[:, :, None] * D[:, None, :]
                       * (fp.sigma_L ** 2)[:, None, None])
    # the point: the peak's stereo and ToF means, each with every term of its σ
    # (scatter, pixel location, background, first-photon model), combined by
    # their range variances (a stereo mean near the beam's vanishing point,
    # σ of metres, then leaves the ToF alone instead of dragging the mean)
    mean["stereo"] = _with_turning(acc, st.range_per_px, mean["stereo"], turn)
    mean["fused"] = fuse_along_ray(mean["stereo"], mean["tof"])
    return PeakMeans(acc.system, acc.k, acc.rows, acc.cols, acc.peak_code,
                     mean["stereo"], mean["tof"], n, s.detections, s.window, s.code,
                     birge, st.range_per_px,
                     None if fp is None else fp.delay, None if fp is None else fp.mu)


def _with_turning(acc, range_per_px, stereo, turn=None):
    """The stereo mean ``(x, C)`` at the peaks where the scan turns inside the
    footprint (``acc.turning``).  Where their angle was solved (``turn``, a
    :class:`~mems_stereo.pipeline.turning_angle.TurningAngles`; None: none), every
    error of the mean angle reaches the solved angle divided by the slope ``dem/dδ``:
    C scaled by ``1/slope²``.  Elsewhere (a pixel the spot's tail alone lights, or no
    first-photon model) a systematic σ of :data:`TURNING_PIXEL_SIGMA` pixels along the
    stereo's m per pixel ``range_per_px`` (Q, 3) (None: unchanged): the shots bunch at
    the turning point, one edge of the footprint, whose image lies up to the spot's
    reach (about a pixel) from the pixel's centre; the time of flight is not off (each
    return lies on its own shot's ray), and the fused point leans on it."""
    turning = acc.turning
    if range_per_px is None or not np.any(turning):
        return stereo
    x, C = stereo
    if turn is not None and np.any(turn.solved):
        C = C / np.where(turn.solved, turn.slope ** 2, 1.0)[:, None, None]
        turning = turning & ~turn.solved
    J = np.where(turning[:, None], np.nan_to_num(range_per_px), 0.0)
    add = TURNING_PIXEL_SIGMA ** 2 * J[:, :, None] * J[:, None, :]
    return (x, C + add)


def _stereo_less_bias(acc, fp, Jt, stereo, birge, grid):
    """``(MeanAngleStereo, (x, C), TurningAngles)``: the stereo at each peak's mean angle
    less its expected bias (``fp`` the :class:`FirstPhotonCorrection`), removed where
    significant (:func:`_significant_bias`; everywhere in a frame:
    :func:`~mems_stereo.pipeline.frame_bias.every_bias_removed`) and at the turning
    peaks whose footprint's angle is solved
    (:func:`~mems_stereo.pipeline.turning_angle.turning_angles`); at those the mean
    angle's statistical covariance ``C`` is the firings' binomial variance given the
    shots (``var_em``) along ``Jt`` (Q, 3) m/rad."""
    s = acc.sums
    n = s.n
    removed = (np.ones(n.shape, bool) if removing_every_bias()
               else _significant_bias(acc, Jt, stereo[1], birge, fp.angle_bias))
    turn = turning_angles(acc, fp.mu, s.theta / n)
    st = stereo_at_mean_angle(acc.system, acc.rows, acc.cols, s.theta, n, stereo[0],
                              step=grid, removed=removed | turn.solved,
                              angle_bias=np.where(turn.solved, turn.bias, fp.angle_bias))
    C = stereo[1]
    if np.any(turn.solved):
        q = turn.solved
        C = C.copy()
        C[q] = (turn.var_em[q] * acc.step_grid[1] ** 2)[:, None, None] \
            * Jt[q, :, None] * Jt[q, None, :]
    return st, (st.point, C), turn


def _significant_bias(acc, Jt, cov_stereo, birge, angle_bias):
    """(Q,) bool: where the mean angle's expected bias is removed, beyond k of the mean
    angle's statistical σ (below it the correction is within the noise, and it rests
    on the system's geometry: a wrong system, e.g. the samples' nominal one, predicts
    wrong small biases); where not removed it stays in σ.  ``Jt`` (Q, 3) m/rad, ∂x/∂θ
    of the stereo at the mean angle (:func:`stereo_angle_jacobian`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        sig_th = np.sqrt(np.einsum("qi,qij,qj->q", Jt, cov_stereo, Jt)
                         * birge) / np.einsum("qi,qi->q", Jt, Jt)
        return np.abs(angle_bias) > acc.k * np.nan_to_num(sig_th, nan=np.inf)


def _with_angle_background(acc, n, W, Jt, stereo):
    """The stereo mean ``(x, C)`` with the spread the subtracted background's Poisson
    fluctuation gives its mean angle, Σ b (θ_b − θ̄)² / n², along ∂x/∂θ there (``Jt``
    (Q, 3) m/rad, :func:`stereo_angle_jacobian` at the mean angle)."""
    s = acc.sums
    with np.errstate(invalid="ignore", divide="ignore"):
        th_bar = s.theta / n
        var_th = np.maximum(s.b2 - 2 * th_bar * s.b1 + th_bar ** 2 * s.b0, 0.0) / W ** 2
    add = np.nan_to_num(var_th)[:, None, None] * Jt[:, :, None] * Jt[:, None, :]
    return (stereo[0], stereo[1] + np.nan_to_num(add))


def _stereo_at_mean_angle(acc, n, stereo, grid):
    """The stereo point at the peaks' mean scan angle
    (:func:`~mems_stereo.pipeline.peak_geometry.stereo_at_mean_angle`) and the stereo
    mean ``(x, C)`` moved there, with the mean angle's covariance propagated at that
    angle where finite (the detections and the subtracted background count as
    independent entries, as in the sums)."""
    s = acc.sums
    st = stereo_at_mean_angle(acc.system, acc.rows, acc.cols, acc.sums.theta, n,
                              stereo[0], step=grid)
    C_st = stereo_cov_at_mean_angle(acc.system, acc.rows, acc.cols, s.theta, n,
                                    s.detections + s.b0, acc.spreads)
    okc = np.all(np.isfinite(C_st), axis=(1, 2))
    return st, (st.point, np.where(okc[:, None, None], C_st, stereo[1]))
