"""The true MEMS trajectory and what the zero-crossing monitor records.

Conventions of :mod:`mems_stereo.model.scanner`: the monitor's phase is

    φ_mon(t) = phase + 2π f_mech · (τ + ½ · drift · τ²),   τ = t − t_ref,

i.e. the instantaneous frequency ``f_mech · (1 + drift · τ)`` drifts linearly
(``drift`` in 1/s, relative).  The monitor's signal ``cos φ_mon`` falls
through zero at φ_mon ≡ π/2 and rises at φ_mon ≡ 3π/2; the true mechanical
angle lags it by the scanner's ``phase_offset``:

    θ(t) = θ0 + θ_mech,max · cos(φ_mon(t) + phase_offset).

So :func:`mems_stereo.model.scanner.scan_angles` with the *true* scanner recovers
θ from the recorded crossings (up to the monitor's timing jitter).

With the hardware model (``docs/hardware.md``) the true scanner's harmonics
make θ(t) = θ0 + θ_mech,max · g(φ_mon(t) + phase_offset) and the monitor fire
at the roots of g (:func:`mems_stereo.model.trajectory.zero_crossing_phases`);
its edge delays make each recorded crossing late by its edge's delay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import OptionError
from mems_stereo.model.system import Scanner
from mems_stereo.model.trajectory import trajectory_shape, zero_crossing_phases


@dataclass(frozen=True)
class Trajectory:
    """Parameters of the true scan: φ_mon(t) and θ(t) as in the module docstring.

    f_mech : Hz; phase : rad, φ_mon at ``t_ref``; drift : 1/s, relative
    frequency drift rate; t_ref : s; theta0, amplitude, phase_offset : rad;
    harmonics : the scanner's (:class:`~mems_stereo.model.hardware.Harmonic`);
    monitor : its :class:`~mems_stereo.model.hardware.MonitorEdges` or None.
    """

    f_mech: float
    phase: float
    drift: float
    t_ref: float
    theta0: float
    amplitude: float
    phase_offset: float
    harmonics: tuple = ()
    monitor: object = None

    @classmethod
    def from_scanner(cls, scanner: Scanner, phase: float, drift: float = 0.0,
                     t_ref: float = 0.0, amplitude: float | None = None) -> Trajectory:
        amp = scanner.theta_mech_max if amplitude is None else float(amplitude)
        return cls(float(scanner.f_mech), float(phase), float(drift), float(t_ref),
                   float(scanner.theta0), amp, float(scanner.phase_offset),
                   tuple(scanner.harmonics), scanner.monitor)

    def monitor_phase(self, t) -> np.ndarray:
        """φ_mon(t), rad, same shape as ``t`` (s)."""
        tau = np.asarray(t, dtype=np.float64) - self.t_ref
        return self.phase + 2.0 * np.pi * self.f_mech * (tau + 0.5 * self.drift * tau * tau)

    def theta(self, t) -> np.ndarray:
        """True scan angle θ(t), rad."""
        if self.harmonics:
            phi = self.monitor_phase(t) + self.phase_offset
            return self.theta0 + self.amplitude * trajectory_shape(phi, self.harmonics)
        return self.theta0 + self.amplitude * np.cos(self.monitor_phase(t) + self.phase_offset)

    def time_of_phase(self, phi) -> np.ndarray:
        """Inverse of :meth:`monitor_phase` (the root nearest t_ref), s.

        Solves ½·drift·τ² + τ = c with c = (φ − phase) / (2π f_mech) in the
        cancellation-free form τ = 2c / (1 + √(1 + 2·drift·c)).
        """
        c = (np.asarray(phi, dtype=np.float64) - self.phase) / (2.0 * np.pi * self.f_mech)
        disc = 1.0 + 2.0 * self.drift * c
        if np.any(disc <= 0):
            raise OptionError("drift: the frequency would reach zero inside the recording")
        return self.t_ref + 2.0 * c / (1.0 + np.sqrt(disc))

    def zero_crossings(self, t_start: float, t_stop: float):
        """Exact crossings of the monitor signal in [t_start, t_stop].

        Returns (Z,) float64 times (s) and (Z,) uint8 rising flags.
        """
        p0, p1 = self.monitor_phase(np.array([t_start, t_stop]))
        if self.harmonics:
            return self._crossings_with_harmonics(p0, p1)
        m0 = math.ceil((p0 - 0.5 * np.pi) / np.pi)
        m1 = math.floor((p1 - 0.5 * np.pi) / np.pi)
        m = np.arange(m0, m1 + 1)
        t = self.time_of_phase(0.5 * np.pi + m * np.pi)
        rising = (np.mod(m, 2) == 1).astype(np.uint8)
        return t, rising

    def _crossings_with_harmonics(self, p0: float, p1: float):
        """Crossings of g(φ_mon) in [p0, p1]: falling at φ_f + 2πj, rising at φ_r + 2πj."""
        pf, pr = zero_crossing_phases(self.harmonics)
        ph, rs = [], []
        for base, flag in ((pf, 0), (pr, 1)):
            j = np.arange(math.ceil((p0 - base) / (2 * np.pi)),
                          math.floor((p1 - base) / (2 * np.pi)) + 1)
            ph.append(base + 2 * np.pi * j)
            rs.append(np.full(j.size, flag, np.uint8))
        phase = np.concatenate(ph)
        order = np.argsort(phase, kind="stable")
        return self.time_of_phase(phase[order]), np.concatenate(rs)[order]


def monitor_zero_crossings(traj: Trajectory, shot_time: np.ndarray, rng: np.random.Generator,
                           jitter: float = 20e-9, margin_periods: float = 1.0):
    """Zero crossings the monitor records around the shots, with timing jitter.

    The span reaches ``margin_periods`` mechanical periods beyond the first
    and last shot, so every shot has a known scan angle.  Jitter is Gaussian
    with standard deviation ``jitter`` (s).  Returns ``(times (Z,), rising (Z,) uint8)``.
    """
    period = 1.0 / traj.f_mech
    t0 = float(shot_time[0]) - margin_periods * period
    t1 = float(shot_time[-1]) + margin_periods * period
    t, rising = traj.zero_crossings(t0, t1)
    if traj.monitor is not None:  # each edge late by its delay (docs/hardware.md)
        t = t + np.where(rising == 1, traj.monitor.rising_delay, traj.monitor.falling_delay)
    if jitter > 0:
        t = t + rng.normal(0.0, jitter, size=t.shape)
        order = np.argsort(t, kind="stable")  # jitter << half a period: order kept in practice
        t, rising = t[order], rising[order]
    return t, rising
