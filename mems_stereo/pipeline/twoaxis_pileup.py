"""The first-photon (pile-up) correction of the two-axis pipeline's peaks."""

from __future__ import annotations

import numpy as np

from mems_stereo.geometry.gating import Gate
from mems_stereo.model.system import System


def pileup_correction(system: System, peaks, gate: Gate, d_scan: np.ndarray,
                      timing_jitter: float, spot=None):
    """Correct each peak's path length for the first-photon (pile-up) bias.

    A pixel that receives m return photons in a shot records the *first* one,
    earlier than the pulse centre on average by D(m) =
    :func:`~mems_stereo.physics.first_photon.first_photon_mean_delay` (m) − D(0).
    For each peak, every read shot k gives the pixel the share f_k of the spot
    whose centre is the image of the beam point at the peak's path length
    (Gaussian spot of :class:`~mems_stereo.physics.spot.SpotModel`, σ at that
    range); the spot's mean photon number μ solves
    ``Σ_k (1 − exp(−μ f_k)) = counts − background`` (bisection), and the
    peak's bias is the detection-weighted mean of D(μ f_k).

    ``peaks`` : :class:`~mems_stereo.pipeline.twoaxis.PixelPeaks` (P peaks);
    ``gate`` : the pixels read in each shot; ``d_scan`` : (K, 3) the shots' beam
    directions; ``timing_jitter`` : s, of the timing σ.
    Returns ``(L_corrected (P,) m, sigma_bias (P,) m, mu (P,))``; the σ is 30 %
    of the correction (μ varies over the pixel's footprint).
    """
    from mems_stereo.physics.first_photon import first_photon_mean_delay
    from mems_stereo.physics.pulse import PulseShape

    P = peaks.pixel.size
    j, f = _spot_fractions(system, peaks, gate, d_scan, spot)
    target = np.maximum(peaks.counts - peaks.background, 0.5)
    lo = np.zeros(P)
    hi = np.full(P, 50.0)
    for _ in range(40):  # Σ_k (1 − exp(−μ f_k)) is increasing in μ
        mid = 0.5 * (lo + hi)
        expect = np.bincount(j, -np.expm1(-mid[j] * f), minlength=P)
        over = expect > target
        hi = np.where(over, mid, hi)
        lo = np.where(over, lo, mid)
    mu = 0.5 * (lo + hi)
    pulse = PulseShape.gaussian(system.laser.pulse_fwhm, timing_jitter)
    grid = np.concatenate([[0.0], np.geomspace(1e-3, 50.0, 120)])
    table = first_photon_mean_delay(np.maximum(grid, 1e-12), pulse)
    table = table - table[0]
    m = mu[j] * f
    pdet = -np.expm1(-m)
    num = np.bincount(j, pdet * np.interp(m, grid, table), minlength=P)
    den = np.bincount(j, pdet, minlength=P)
    with np.errstate(invalid="ignore", divide="ignore"):
        bias_t = np.where(den > 0, num / den, 0.0)  # s, <= 0
    corr = system.speed_of_light * bias_t
    return peaks.L - corr, 0.3 * np.abs(corr), mu


def _spot_fractions(system: System, peaks, gate: Gate, d_scan: np.ndarray, spot=None):
    """``(j, f)``: for every read (shot, peak pixel) with a known beam, the peak index
    ``j`` (N,) int64 and the share ``f`` (N,) of the spot (centred on the image of the
    beam point at the peak's path length) that falls on the pixel; shares of at most
    1e-4 are left out."""
    from scipy.special import ndtr

    from mems_stereo.geometry.triangulation import scanner_ray_point
    from mems_stereo.physics.link_budget import LinkBudget
    from mems_stereo.physics.spot import SpotModel

    rc = system.receiver
    w = rc.image_size[0]
    P = peaks.pixel.size
    idx = np.full(gate.n_pixels, -1, np.int64)
    idx[peaks.pixel] = np.arange(P)
    shot = np.repeat(np.arange(gate.n_shots, dtype=np.int64), gate.counts())
    j = idx[gate.pixels]
    sel = (j >= 0) & np.all(np.isfinite(d_scan[shot]), axis=1)
    shot, j = shot[sel], j[sel]
    # spot centre of each (shot, peak pixel) at the peak's path length
    x = scanner_ray_point(system.scanner.position, d_scan[shot], peaks.L[j])[0]
    K = rc.camera_matrix
    if np.any(rc.dist_coeffs):
        from mems_stereo.model.camera import project_points

        uvc = project_points(x, K, rc.dist_coeffs)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            uvc = np.stack([K[0, 0] * x[:, 0] / x[:, 2] + K[0, 2],
                            K[1, 1] * x[:, 1] / x[:, 2] + K[1, 2]], axis=1)
    spot = SpotModel() if spot is None else spot
    pitch = np.asarray(rc.pixel_pitch, float)
    link = LinkBudget(focal_length=float(K[0, 0] * pitch[0]))
    rng_tx = np.linalg.norm(x - system.scanner.position, axis=1)
    sig = spot.sigma(np.nan_to_num(rng_tx, nan=1.0), np.nan_to_num(x[:, 2], nan=1.0), link)
    pix = peaks.pixel[j]
    du = (pix % w) - uvc[:, 0]
    dv = (pix // w) - uvc[:, 1]
    su, sv = sig / pitch[0], sig / pitch[1]
    f = ((ndtr((du + 0.5) / su) - ndtr((du - 0.5) / su))
         * (ndtr((dv + 0.5) / sv) - ndtr((dv - 0.5) / sv)))
    f = np.nan_to_num(f, nan=0.0)
    keep = f > 1e-4
    f, j = f[keep], j[keep]
    return j, f
