"""Optical link budget: emitted photons, and signal photons returned to a pixel per shot.

The paper's system (Table 1) by default.  Used by the simulator, and by
anyone who wants the expected signal level of a system.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.model.system import Receiver
from mems_stereo.physics.pulse import PulseShape

PLANCK = 6.62607015e-34  # J s
C_VACUUM = 299792458.0  # m/s


# --------------------------------------------------------------------------
# link budget


@dataclass(frozen=True)
class LinkBudget:
    """Parameters of the optical link (defaults: the paper's system, Table 1).

    Parameters
    ----------
    peak_power : W, laser peak optical power (80 mW).
    mems_reflectivity : mirror reflectivity at the wavelength (81.25 %).
    focal_length : m, receiver lens (8 mm); f_number : (2) → aperture Ø f/N = 4 mm.
    optics_transmission : lens and window transmission (0.7).
    filter_transmission : 10 nm band-pass at the laser line, including the
        laser diode's spectral width and drift (0.5).
    pde : photon detection efficiency of a SPAD at 659 nm (0.20).
    fill_factor : photosensitive share of a pixel; None → spads_per_pixel
        SPADs of the receiver's ``spad_diameter`` over the pixel area
        (4 · π · (6 µm)² / (40.56 µm · 209.6 µm) = 5.3 %).
    spads_per_pixel : 4 (SPADEye2).
    """

    peak_power: float = 0.080
    mems_reflectivity: float = 0.8125
    focal_length: float = 8e-3
    f_number: float = 2.0
    optics_transmission: float = 0.7
    filter_transmission: float = 0.5
    pde: float = 0.20
    fill_factor: float | None = None
    spads_per_pixel: int = 4

    @property
    def aperture_area(self) -> float:
        """m², entrance pupil area π (f / 2N)²."""
        return math.pi * (self.focal_length / (2.0 * self.f_number)) ** 2

    def pixel_fill_factor(self, receiver: Receiver) -> float:
        if self.fill_factor is not None:
            return float(self.fill_factor)
        spad = self.spads_per_pixel * math.pi * (0.5 * receiver.spad_diameter) ** 2
        return min(1.0, spad / float(np.prod(receiver.pixel_pitch)))

    def receiver_efficiency(self, receiver: Receiver) -> float:
        """Optics × filter × PDE × fill factor (dimensionless)."""
        return (self.optics_transmission * self.filter_transmission * self.pde
                * self.pixel_fill_factor(receiver))


def emitted_photons(budget: LinkBudget, pulse: PulseShape, wavelength: float) -> float:
    """Photons leaving the mirror per pulse: P_peak · ∫shape dt / (h c / λ) · R_MEMS."""
    energy = budget.peak_power * pulse.energy_time
    return energy * wavelength / (PLANCK * C_VACUUM) * budget.mems_reflectivity


def expected_signal_photons(n_emitted: float, reflectivity, cos_emit, cos_view, range_rx,
                            budget: LinkBudget, receiver: Receiver) -> np.ndarray:
    """Mean detected signal photons per shot over the whole returned spot.

    Lambertian target (the whole beam hits it):
    ``μ = N_emit · ρ · cos θ_e / π · A_ap · cos θ_r / R² · η_rx``, where θ_e is
    the angle between the surface normal and the direction to the receiver,
    θ_r the angle of the returning ray to the optical axis, R the distance
    target → projection centre (m) and η_rx :meth:`LinkBudget.receiver_efficiency`.
    Inputs (N,) arrays; returns (N,) float64 (0 where cos θ_e ≤ 0).
    """
    ce = np.clip(np.asarray(cos_emit, float), 0.0, None)
    cv = np.clip(np.asarray(cos_view, float), 0.0, None)
    r = np.asarray(range_rx, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = (n_emitted * np.asarray(reflectivity, float) * ce / math.pi
              * budget.aperture_area * cv / (r * r) * budget.receiver_efficiency(receiver))
    return np.where(np.isfinite(mu), mu, 0.0)
