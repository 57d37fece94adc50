"""The calibration's share of a fused point's covariance: ``J Σ Jᵀ``, once per point.

A system written by ``calibrate`` carries the covariance Σ (P, P) of its free
parameters (JSON ``calibration.covariance``, ``{names, matrix}``, SI units).  An
error in those parameters moves every detection of a peak alike, so it is not
averaged down with the peak's n detections: it is added once to each fused
point's covariance, ``C ← C + J Σ Jᵀ``, with ``J`` (3, P) the sensitivity of the
point (receiver camera frame, m per parameter unit) to the parameters at fixed
measurements — the pixel ``(u, v)``, the TDC code and the scan phase.

``J`` comes from central differences of the package's own triangulation
(:func:`~mems_stereo.geometry.uncertainty.stereo_point_est`,
:func:`~mems_stereo.geometry.uncertainty.tof_point`, fused with the peak's stereo
weight) at the measurements that give the fused point with the nominal system:
the scan angle of the ray through it, the path length ``L = |x − p| + |x|``, the
code of that ``L`` (:func:`~mems_stereo.model.tdc.detection_codes`), and for each
of the two sweeps through that angle the time since its half period's start
crossing (the recorded crossing times are fixed; a changed system moves the
crossings' phases and edge delays and so the interpolated phase, as
:func:`~mems_stereo.model.scanner.phase_from_zero_crossings` does).  The sweeps'
mean ``J_e`` moves every detection alike; their half difference ``J_o`` (a phase
shift moves the two sweeps' angles oppositely) moves a peak's mean only by its
detections' imbalance between the sweeps (see :func:`calibration_point_covariance`).
``f_mech`` does not enter processing (phases are interpolated between crossings)
and contributes nothing.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.geometry.uncertainty import stereo_point_est, tof_point
from mems_stereo.model.scanner import scan_angle_from_phase
from mems_stereo.model.system import System
from mems_stereo.model.tdc import detection_codes, detection_path_length
from mems_stereo.model.trajectory import (
    trajectory_shape,
    trajectory_slope,
    zero_crossing_phases,
)

#: central-difference step of each parameter, as a fraction of its σ
STEP_OF_SIGMA = 1e-3
#: Newton iterations that invert the trajectory's harmonics for the scan phase
PHASE_ITERATIONS = 4


def calibration_covariance(system: System):
    """``(names (P,) tuple, Σ (P, P) float64)`` of the system's calibration, or None
    when it carries no covariance (or an empty one)."""
    cal = system.calibration
    if not isinstance(cal, dict) or not isinstance(cal.get("covariance"), dict):
        return None
    names = tuple(cal["covariance"].get("names", ()))
    if not names:
        return None
    cov = np.asarray(cal["covariance"]["matrix"], dtype=np.float64).reshape(len(names),
                                                                            len(names))
    return names, cov


def _scan_angle_of_points(system: System, x: np.ndarray) -> np.ndarray:
    """(Q,) rad: the scan angle whose ray from the scanner passes through ``x`` (Q, 3)
    (the mirror normal is parallel to ``l − d``; the branch nearest θ0)."""
    sc = system.scanner
    d = x - np.asarray(sc.position, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = np.asarray(sc.laser_direction, dtype=np.float64) - d
    B = np.asarray(sc.normal_basis, dtype=np.float64)
    th = np.arctan2(n @ B[1], n @ B[0])
    return th + np.pi * np.round((sc.theta0 - th) / np.pi)


def _scan_phases(system: System, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two monitor phases (Q,) each (one per sweep direction) of scan angles ``theta``."""
    sc = system.scanner
    c = np.clip((theta - sc.theta0) / sc.theta_mech_max, -1.0, 1.0)
    out = []
    for sign in (1.0, -1.0):
        phi = sign * np.arccos(c)
        for _ in range(PHASE_ITERATIONS if sc.harmonics else 0):
            g = trajectory_shape(phi, sc.harmonics) - c
            s = trajectory_slope(phi, sc.harmonics)
            phi = phi - np.where(np.abs(s) > 1e-9, g / np.where(s == 0, 1.0, s), 0.0)
        out.append(phi - sc.phase_offset)
    return out[0], out[1]


def _half_ends(system: System, after_rising: np.ndarray):
    """(start, end) phases (Q,) rad of each measurement's half period (falling → rising
    crossing, or rising → the next falling) and (start, end) edge delays (Q,) s."""
    pf, pr = zero_crossing_phases(system.scanner.harmonics)
    mon = system.scanner.monitor
    df, dr = (0.0, 0.0) if mon is None else (mon.falling_delay, mon.rising_delay)
    start = np.where(after_rising, pr, pf)
    end = np.where(after_rising, pf + 2.0 * np.pi, pr)
    return (start, end), (np.where(after_rising, dr, df), np.where(after_rising, df, dr))


class _Sweep:
    """One sweep direction's fixed measurement: the time since its half period's
    (true) start crossing, fixed by the recorded crossings; the phase it gives with
    another system's trajectory and edge delays follows the pipeline's interpolation
    between crossings (:func:`~mems_stereo.model.scanner.phase_from_zero_crossings`)."""

    def __init__(self, system: System, phase: np.ndarray):
        pf, _ = zero_crossing_phases(system.scanner.harmonics)
        phi = pf + np.mod(phase - pf, 2.0 * np.pi)
        self.after_rising = phi >= zero_crossing_phases(system.scanner.harmonics)[1]
        (start, end), self.delays = _half_ends(system, self.after_rising)
        omega = 2.0 * np.pi * system.scanner.f_mech
        self.tau = (phi - start) / omega
        self.T = (end - start) / omega

    def theta(self, system: System) -> np.ndarray:
        """(Q,) rad: the scan angle of the measurement with ``system``."""
        (start, end), (ds, de) = _half_ends(system, self.after_rising)
        ds0, de0 = self.delays
        a = (self.tau + ds - ds0) / (self.T + (ds - ds0) - (de - de0))
        return scan_angle_from_phase(start + a * (end - start), system.scanner)


class _Measurements:
    """The fixed measurements of Q fused points: pixel, code, the two sweeps, weight."""

    def __init__(self, system: System, x, rows, cols, w):
        W = system.receiver.width
        self.u = np.asarray(cols, dtype=np.float64)
        self.v = np.asarray(rows, dtype=np.float64)
        self.pixel = None if system.tdc.pixel_offsets is None else (
            np.asarray(rows, np.int64) * W + np.asarray(cols, np.int64))
        p = np.asarray(system.scanner.position, dtype=np.float64)
        L = np.linalg.norm(x - p, axis=1) + np.linalg.norm(x, axis=1)
        self.code = detection_codes(L, system, self.pixel)
        self.sweeps = [_Sweep(system, ph)
                       for ph in _scan_phases(system, _scan_angle_of_points(system, x))]
        self.w = np.asarray(w, dtype=np.float64)[:, None]

    def points(self, system: System) -> list:
        """The fused point (Q, 3) m of these measurements with ``system``, one per sweep."""
        L = detection_path_length(self.code, system, self.pixel)
        out = []
        for sweep in self.sweeps:
            th = sweep.theta(system)
            xs = stereo_point_est(system, self.u, self.v, L, th)
            xt = tof_point(system, self.u, self.v, L, th)
            out.append(self.w * np.nan_to_num(xs) + (1.0 - self.w) * np.nan_to_num(xt))
        return out


def calibration_point_covariance(system: System, x, rows, cols, w, n) -> np.ndarray | None:
    """(Q, 3, 3) float64 m²: the calibration's covariance of fused points ``x`` (Q, 3) m
    at pixels ``rows``, ``cols`` (Q,) with stereo weights ``w`` (Q,) and ``n`` (Q,)
    detections, from the system's calibration covariance Σ; None without one.

    ``C = J_e Σ J_eᵀ + J_o Σ J_oᵀ / n`` with ``J_e``, ``J_o`` (3, P) the mean and half
    the difference of the two sweeps' sensitivities (module docstring): a peak's
    detections split between the sweeps as a fair binomial, so the odd part moves its
    mean by ``(2f − 1)·J_o δ`` with ``E[(2f − 1)²] = 1/n``.  Rows whose point is not
    finite are 0."""
    cal = calibration_covariance(system)
    if cal is None:
        return None
    names, cov = cal
    x = np.asarray(x, dtype=np.float64)
    good = np.all(np.isfinite(x), axis=1) & np.isfinite(np.asarray(w, np.float64))
    out = np.zeros((x.shape[0], 3, 3))
    if not np.any(good):
        return out
    m = _Measurements(system, x[good], np.asarray(rows)[good], np.asarray(cols)[good],
                      np.asarray(w)[good])
    J = np.empty((2, int(good.sum()), 3, len(names)))
    for i, name in enumerate(names):
        v0 = system.get_param(name)
        sd = float(np.sqrt(max(cov[i, i], 0.0)))
        h = STEP_OF_SIGMA * sd if sd > 0 else 1e-6 * max(1.0, abs(v0))
        plus = m.points(system.with_params(**{name: v0 + h}))
        minus = m.points(system.with_params(**{name: v0 - h}))
        for b in range(2):
            J[b, :, :, i] = (plus[b] - minus[b]) / (2.0 * h)
    Je, Jo = 0.5 * (J[0] + J[1]), 0.5 * (J[0] - J[1])
    n_good = np.maximum(np.asarray(n, dtype=np.float64)[good], 1.0)
    C = (np.einsum("qip,pk,qjk->qij", Je, cov, Je)
         + np.einsum("qip,pk,qjk->qij", Jo, cov, Jo) / n_good[:, None, None])
    out[good] = np.nan_to_num(C)
    return out
