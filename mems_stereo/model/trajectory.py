"""The mirror's trajectory beyond the cosine, and the monitor's edge delays.

The hardware model of ``docs/hardware.md``: with harmonics (:class:`Harmonic`)
the mechanical angle is

    θ_mech(φ) = θ_mech,max · g(φ + phase_offset),
    g(φ) = cos φ + Σ_k A_k · cos(k φ + ψ_k),

φ the monitor's phase, linear in time between recorded crossings.  The monitor
fires where its signal g(φ) crosses zero: near φ = π/2 (falling) and 3π/2
(rising), at the roots :func:`zero_crossing_phases` gives (exactly π/2 and 3π/2
without harmonics).  With :class:`MonitorEdges` each recorded crossing is late
by its edge's delay, which :func:`true_crossing_times` removes.  Odd harmonics
keep the two roots π apart; even ones move them towards each other.
"""

from __future__ import annotations

import math

import numpy as np

from mems_stereo.errors import GeometryError
from mems_stereo.model.hardware import Harmonic, MonitorEdges, Scanner

__all__ = ["Harmonic", "MonitorEdges", "crossing_phases_model", "trajectory_shape",
           "trajectory_slope", "true_crossing_times", "zero_crossing_phases"]


def _terms(harmonics):
    k = np.array([h.order for h in harmonics], dtype=np.float64)
    a = np.array([h.amplitude for h in harmonics], dtype=np.float64)
    p = np.array([h.phase for h in harmonics], dtype=np.float64)
    return k, a, p


def trajectory_shape(phi, harmonics) -> np.ndarray:
    """g(φ) = cos φ + Σ A_k cos(k φ + ψ_k), the trajectory in units of θ_mech,max.

    ``phi`` (...) rad; ``harmonics`` a sequence of :class:`Harmonic`.
    Returns float64 of ``phi``'s shape (NaN where φ is NaN).
    """
    phi = np.asarray(phi, dtype=np.float64)
    g = np.cos(phi)
    for h in harmonics:
        g = g + h.amplitude * np.cos(h.order * phi + h.phase)
    return g


def trajectory_slope(phi, harmonics) -> np.ndarray:
    """dg/dφ = −sin φ − Σ k A_k sin(k φ + ψ_k), same shape as ``phi``."""
    phi = np.asarray(phi, dtype=np.float64)
    d = -np.sin(phi)
    for h in harmonics:
        d = d - h.order * h.amplitude * np.sin(h.order * phi + h.phase)
    return d


def zero_crossing_phases(harmonics) -> tuple[float, float]:
    """(φ_falling, φ_rising), rad: the roots of g near π/2 and 3π/2.

    Newton's method from π/2 and 3π/2 (g' ≈ ∓1 there); raises
    :class:`~mems_stereo.errors.GeometryError` when a root is not found or the
    trajectory does not cross in the expected direction (harmonics so strong
    that the mirror turns back before its zero crossing).
    """
    if not harmonics:
        return 0.5 * math.pi, 1.5 * math.pi
    phi = np.array([0.5 * math.pi, 1.5 * math.pi])
    for _ in range(60):
        step = trajectory_shape(phi, harmonics) / trajectory_slope(phi, harmonics)
        phi = phi - step
        if np.all(np.abs(step) < 1e-15):
            break
    slope = trajectory_slope(phi, harmonics)
    if (not np.all(np.isfinite(phi)) or np.any(np.abs(trajectory_shape(phi, harmonics)) > 1e-12)
            or slope[0] >= 0 or slope[1] <= 0
            or np.any(np.abs(phi - np.array([0.5, 1.5]) * math.pi) > 0.5)):
        raise GeometryError("scanner.harmonics: expected a trajectory that falls through "
                            "zero near φ = π/2 and rises near 3π/2 (harmonics too strong)")
    return float(phi[0]), float(phi[1])


def crossing_phases_model(ideal_phases, rising, harmonics) -> np.ndarray:
    """The crossings' phases with harmonics, (Z,) float64 rad.

    ``ideal_phases`` (Z,): :func:`mems_stereo.model.scanner.crossing_phases` (π/2 or
    3π/2 mod 2π); each is moved to its kind's root of g (:func:`zero_crossing_phases`).
    The shifts are below π/2, so the order and the count of periods are kept.
    """
    pf, pr = zero_crossing_phases(harmonics)
    r = np.asarray(rising, dtype=bool)
    return np.asarray(ideal_phases, np.float64) + np.where(r, pr - 1.5 * math.pi,
                                                          pf - 0.5 * math.pi)


def true_crossing_times(zero_crossings, rising, monitor: MonitorEdges | None) -> np.ndarray:
    """Recorded crossing times less their edge's delay, (Z,) float64 s.

    Raises :class:`~mems_stereo.errors.GeometryError` when the corrected times are
    no longer increasing (delays of half a period or more).
    """
    zc = np.asarray(zero_crossings, dtype=np.float64)
    if monitor is None:
        return zc
    out = zc - np.where(np.asarray(rising, bool), monitor.rising_delay, monitor.falling_delay)
    if out.size > 1 and np.any(np.diff(out) <= 0):
        raise GeometryError("scanner.monitor: the edge delays reorder the recorded zero "
                            "crossings (expected delays well below half a mirror period)")
    return out


def mechanical_angle(phase, scanner: Scanner) -> np.ndarray:
    """θ_mech = θ_mech,max · g(φ + phase_offset), rad, for monitor phases ``phase``."""
    phi = np.asarray(phase, dtype=np.float64) + scanner.phase_offset
    return scanner.theta_mech_max * trajectory_shape(phi, scanner.harmonics)


def harmonics_rms(harmonics: tuple[Harmonic, ...]) -> float:
    """RMS over a period of g(φ) − cos φ (relative to θ_mech,max): √(Σ A_k² / 2)."""
    return math.sqrt(sum(h.amplitude ** 2 for h in harmonics) / 2.0)
