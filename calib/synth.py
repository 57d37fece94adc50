"""Synthetic flat-target detections for tests and examples (no HDF5, no classifier).

The photon model is the hardware's: a Gaussian pulse of FWHM ``pulse_fwhm``
centred at TDC time ``τ0 = L/c + offset``; Poisson signal photons (mean μ per
shot), Poisson background (rate λ) from the TDC start on; the pixel records
its first photon only; photons before the TDC start (τ < 0) are lost; codes
``N = floor(τ / bin_width) + 1``.  The beam spot is a point: it lights the
pixel that contains the projection of the hit point.  Labels are the truth
(signal = the first photon was a laser photon), as a perfect classifier
would give.
"""

from __future__ import annotations

import numpy as np
from mems_stereo.calib.detections import TargetDetections
from mems_stereo.calib.model import beam_hits, plane_normal

from mems_stereo.model.system import System
from mems_stereo.physics.pulse import pulse_sigma


def synthetic_target(system: System, alpha: float, dist: float, n_shots: int,
                     rng: np.random.Generator, mu: float = 1.0, lam: float = 0.0,
                     jitter: float = 0.0, phase0: float = 0.3, beta: float = 0.0,
                     source: str = "<synthetic>") -> TargetDetections:
    """Detections of ``n_shots`` shots on the plane n(α, β)·x = dist seen by ``system``.

    Parameters
    ----------
    system : the TRUE system (what the hardware is).
    alpha, beta : rad, plane tilts (:func:`mems_stereo.calib.model.plane_normal`).
    dist : m, the plane's distance from the projection centre.
    n_shots : shots at f_rep, monitor phase φ_k = 2π f_mech k / f_rep + phase0.
    rng : numpy Generator.
    mu : mean signal photons per shot in the lit pixel.
    lam : background rate per pixel, Hz.
    jitter : σ of the SPAD timing jitter, s.
    """
    k = np.arange(int(n_shots))
    phase = 2.0 * np.pi * system.scanner.f_mech / system.laser.f_rep * k + phase0
    n = np.broadcast_to(plane_normal(alpha, beta), (k.size, 3))
    hits = beam_hits(system, {}, phase, n, np.full(k.size, float(dist)))
    w, h = system.receiver.image_size
    col = np.rint(hits.pixel[:, 0])
    row = np.rint(hits.pixel[:, 1])
    on = hits.ok & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    tau0 = hits.path / system.speed_of_light + system.tdc.offset
    sig = pulse_sigma(system.laser.pulse_fwhm, jitter)
    window = system.tdc.n_bins * system.tdc.bin_width
    # signal photons: Poisson count, Gaussian times; keep the first inside the window
    n_ph = rng.poisson(mu, size=k.size) * on
    t_ph = np.repeat(tau0, n_ph) + sig * rng.standard_normal(int(n_ph.sum()))
    t_ph[(t_ph < 0) | (t_ph >= window)] = np.inf
    first_sig = np.full(k.size, np.inf)
    idx = np.repeat(np.arange(k.size), n_ph)
    np.minimum.at(first_sig, idx, t_ph)
    first_bg = rng.exponential(1.0 / lam, size=k.size) if lam > 0 else np.full(k.size, np.inf)
    is_sig = np.isfinite(first_sig) & (first_sig < first_bg)
    code = (np.floor(first_sig[is_sig] / system.tdc.bin_width) + 1).astype(np.int64)
    shots = np.flatnonzero(is_sig)
    noise = (1.0 - np.exp(-lam * window)) if lam > 0 else 0.0
    return TargetDetections(phase, is_sig, shots, col[shots], row[shots], code, float(noise),
                            int(w * h), source)
