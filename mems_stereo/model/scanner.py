"""The resonant MEMS scanner: trajectory, scan angle per shot, reflection law.

Conventions (``docs/conventions.md``):

* mechanical angle ``θ_mech(t) = θ_mech,max · cos φ(t)`` (paper Eq. 1 with
  ``φ(t) = 2π f_mech t + φ0``); scan angle ``θ = θ0 + θ_mech``;
* θ_mech falls through zero at ``φ ≡ π/2`` and rises through zero at
  ``φ ≡ 3π/2`` (mod 2π); the zero-crossing monitor records both kinds;
* mirror normal ``n(θ) = cos θ · e1 + sin θ · e2``; scan direction by the
  reflection law ``d_scan = d_laser − 2 (n·d_laser) n`` (paper Eq. 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError, GeometryError
from mems_stereo.model.hardware import Scanner, validate_normal_basis
from mems_stereo.model.trajectory import (
    crossing_phases_model,
    mechanical_angle,
    true_crossing_times,
)

PHASE_FALLING = 0.5 * math.pi
PHASE_RISING = 1.5 * math.pi


# --------------------------------------------------------------------------
# trajectory


def theta_mech_trajectory(t, theta_mech_max: float, f_mech: float, phi0: float = 0.0):
    """Mechanical angle θ_mech(t) = θ_max · cos(2π f_mech t + φ0), rad.

    ``t`` : array-like, seconds.  Returns an array of the same shape.
    """
    return theta_mech_max * np.cos(2.0 * np.pi * f_mech * np.asarray(t, dtype=np.float64) + phi0)


def theta_mech_samples(n_shots: int, frequency_ratio: float, theta_mech_max: float,
                       phi0: float = 0.0) -> np.ndarray:
    """Paper Eq. 1: θ_mech,k = θ_max · cos(2π (f_mech/f_rep) k + φ0), k = 0..n_shots−1.

    Returns (n_shots,) float64, rad.
    """
    k = np.arange(int(n_shots), dtype=np.float64)
    return theta_mech_max * np.cos(2.0 * np.pi * frequency_ratio * k + phi0)


# --------------------------------------------------------------------------
# zero crossings -> phase -> scan angle


def validate_zero_crossings(zero_crossings, rising, source: str = "",
                            field: str = "/scanner/zero_crossings"):
    """Check the recorded zero crossings; return (Z,) float64 times and (Z,) bool rising.

    Raises :class:`FormatError` when there are fewer than two, when they are
    not finite and strictly increasing, or when ``rising`` does not match.
    """
    zc = np.asarray(zero_crossings, dtype=np.float64)
    if zc.ndim != 1:
        raise FormatError(f"expected a 1-D array of times, found shape {zc.shape}", source, field)
    if zc.size < 2:
        raise FormatError(f"expected at least 2 zero crossings to interpolate the phase, "
                          f"found {zc.size}", source, field)
    if not np.all(np.isfinite(zc)):
        raise FormatError("expected finite times, found NaN or inf", source, field)
    steps = np.diff(zc)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0))
        raise FormatError(f"expected strictly increasing times, found t[{i + 1}] = "
                          f"{float(zc[i + 1])!r} <= t[{i}] = {float(zc[i])!r}", source, field)
    r = np.asarray(rising)
    rfield = field.rsplit("/", 1)[0] + "/rising"
    if r.shape != zc.shape:
        raise FormatError(f"expected shape {zc.shape} like the zero crossings, found {r.shape}",
                          source, rfield)
    if not np.all((r == 0) | (r == 1)):
        raise FormatError("expected 0 (falling) or 1 (rising) only", source, rfield)
    return zc, r.astype(bool)


def crossing_phases(zero_crossings, rising) -> np.ndarray:
    """Unwrapped phase φ at each zero crossing, (Z,) float64, rad.

    A falling crossing has φ ≡ π/2, a rising one φ ≡ 3π/2 (mod 2π).  Each
    crossing gets the smallest such phase above the previous one, so
    alternating crossings step by π and a missed crossing steps by 2π.  The
    first crossing's phase lies in [0, 2π).
    """
    zc, r = validate_zero_crossings(zero_crossings, rising)
    base = np.where(r, PHASE_RISING, PHASE_FALLING)
    # same kind as the previous crossing -> one full period (a crossing was missed)
    step = np.where(r[1:] == r[:-1], 2.0 * np.pi, np.pi)
    phases = np.empty_like(zc)
    phases[0] = base[0]
    phases[1:] = base[0] + np.cumsum(step)
    return phases


def phase_from_zero_crossings(times, zero_crossings, rising, scanner: Scanner | None = None):
    """Scan phase φ at each time, interpolated between recorded zero crossings.

    Parameters
    ----------
    times : (K,) float64, s, e.g. the shot trigger times.
    zero_crossings : (Z,) float64, s, increasing.
    rising : (Z,) 0/1, 1 where θ_mech rose through zero.
    scanner : optional; where it has harmonics or monitor edge delays
        (``docs/hardware.md``) the crossings' times lose their edge's delay and
        their phases are the trajectory's roots
        (:mod:`mems_stereo.model.trajectory`); otherwise it is not used.

    Returns
    -------
    phase : (K,) float64, rad; NaN where the time lies outside the span of the
        crossings (no known phase: never extrapolated).
    valid : (K,) bool.

    The phase is linear between consecutive crossings, so a slow frequency
    drift is followed at the resolution of half a period.

    Examples
    --------
    >>> crossings = np.array([0.0, 0.5e-3, 1.0e-3])          # s
    >>> rising = np.array([1, 0, 1])
    >>> phase, valid = ms.phase_from_zero_crossings(np.array([0.25e-3, 0.75e-3, 2e-3]),
    ...                                             crossings, rising)
    >>> np.round(phase / np.pi, 3), valid
    (array([ 2.,  3., nan]), array([ True,  True, False]))
    """
    zc, r = validate_zero_crossings(zero_crossings, rising)
    phases = crossing_phases(zc, r)
    if scanner is not None and (scanner.harmonics or scanner.monitor is not None):
        zc = true_crossing_times(zc, r, scanner.monitor)
        phases = crossing_phases_model(phases, r, scanner.harmonics)
    t = np.asarray(times, dtype=np.float64)
    valid = (t >= zc[0]) & (t <= zc[-1]) & np.isfinite(t)
    phase = np.full(t.shape, np.nan)
    phase[valid] = np.interp(t[valid], zc, phases)
    return phase, valid


def scan_angle_from_phase(phase, scanner: Scanner) -> np.ndarray:
    """θ = θ0 + θ_max · cos(φ + phase_offset), rad (NaN where φ is NaN); with the
    scanner's harmonics θ = θ0 + θ_max · g(φ + phase_offset)
    (:func:`mems_stereo.model.trajectory.trajectory_shape`)."""
    if scanner.harmonics:
        return scanner.theta0 + mechanical_angle(phase, scanner)
    phi = np.asarray(phase) + scanner.phase_offset
    return scanner.theta0 + scanner.theta_mech_max * np.cos(phi)


def scan_angles(times, zero_crossings, rising, scanner: Scanner):
    """Scan angle θ of every shot from the recorded zero crossings.

    Returns ``(theta, valid)``: (K,) float64 rad (NaN where unknown) and (K,)
    bool.  Shots outside the crossings' span are invalid: report and skip them.

    Examples
    --------
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> theta, valid = ms.scan_angles(rec.shot_time, rec.zero_crossings, rec.rising,
    ...                               rec.system.scanner)
    >>> theta.shape, bool(valid.all()), np.round(theta[:3], 4)
    ((800,), True, array([0.5533, 0.5853, 0.6591]))
    """
    phase, valid = phase_from_zero_crossings(times, zero_crossings, rising, scanner)
    return scan_angle_from_phase(phase, scanner), valid


# --------------------------------------------------------------------------
# mirror and reflection law


def mirror_normal(theta, normal_basis) -> np.ndarray:
    """Unit mirror normal n(θ) = cos θ · e1 + sin θ · e2.

    ``theta`` : (...) rad; ``normal_basis`` : (2, 3) orthonormal.
    Returns (..., 3) float64, world frame.

    Examples
    --------
    >>> basis = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    >>> np.round(ms.mirror_normal(np.pi / 4, basis), 4)
    array([0.7071, 0.    , 0.7071])
    """
    B = validate_normal_basis(normal_basis)
    th = np.asarray(theta, dtype=np.float64)[..., None]
    return np.cos(th) * B[0] + np.sin(th) * B[1]


def reflect(direction, normal) -> np.ndarray:
    """Reflection law (paper Eq. 6): d − 2 (n·d) n.  Shapes broadcast over (..., 3).

    Examples
    --------
    >>> normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)          # a mirror at 45 degrees
    >>> bool(np.allclose(ms.reflect(np.array([-1.0, 0.0, 0.0]), normal), [0.0, 0.0, 1.0]))
    True
    """
    d = np.asarray(direction, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    return d - 2.0 * np.sum(n * d, axis=-1, keepdims=True) * n


def scan_direction(theta, scanner: Scanner) -> np.ndarray:
    """Unit scan direction d_scan(θ), (..., 3) float64, world frame.

    Examples
    --------
    >>> scanner = ms.preset("burkard2022").scanner
    >>> np.round(ms.scan_direction(scanner.theta0, scanner), 4)
    array([0.0499, 0.    , 0.9988])
    """
    d = np.asarray(scanner.laser_direction, dtype=np.float64)
    nd = np.linalg.norm(d)
    if not np.isfinite(nd) or abs(nd - 1.0) > 1e-6:
        raise GeometryError(f"laser_direction: expected a unit vector, found norm {nd:.9g}")
    return reflect(d, mirror_normal(theta, scanner.normal_basis))


def scan_direction_derivative(theta, scanner: Scanner) -> np.ndarray:
    """∂d_scan/∂θ, (..., 3) float64 (per rad), for uncertainty propagation."""
    B = np.asarray(scanner.normal_basis, dtype=np.float64)
    d = np.asarray(scanner.laser_direction, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)[..., None]
    n = np.cos(th) * B[0] + np.sin(th) * B[1]
    dn = -np.sin(th) * B[0] + np.cos(th) * B[1]
    nd = np.sum(n * d, axis=-1, keepdims=True)
    dnd = np.sum(dn * d, axis=-1, keepdims=True)
    return -2.0 * (dnd * n + nd * dn)


# --------------------------------------------------------------------------
# theta0 from the working distance (paper Eq. 5)


def theta0_exact(baseline_x: float, working_distance: float) -> float:
    """θ0 = π/4 − ½·atan(x_M0 / W): transmitter axis crosses the optical axis at z = W.

    Valid for the paper's geometry (laser along −x, normal in the x–z plane,
    mirror at x = −x_M0): the beam at θ0 leaves at 2θ0 from the x axis.

    Examples
    --------
    >>> round(ms.theta0_exact(0.125, 2.0), 6)
    0.754189
    """
    return math.pi / 4 - 0.5 * math.atan(baseline_x / working_distance)


def theta0_small_angle(baseline_x: float, working_distance: float) -> float:
    """Paper Eq. 5: θ0 = π/4 − atan(x_M0 / (2W)) (small-angle form of :func:`theta0_exact`).

    Examples
    --------
    >>> round(ms.theta0_small_angle(0.125, 2.0), 6), round(ms.theta0_exact(0.125, 2.0), 6)
    (0.754158, 0.754189)
    """
    return math.pi / 4 - math.atan(baseline_x / (2.0 * working_distance))


@dataclass(frozen=True)
class TrajectoryCheck:
    """How far a phase model is from the recorded crossings (diagnostics)."""

    n_crossings: int
    mean_frequency: float  # Hz, from the span of the crossings
    max_period_deviation: float  # relative


def describe_zero_crossings(zero_crossings, rising) -> TrajectoryCheck:
    """Mean frequency and period spread of the recorded crossings."""
    zc, r = validate_zero_crossings(zero_crossings, rising)
    ph = crossing_phases(zc, r)
    f = (ph[-1] - ph[0]) / (2 * np.pi * (zc[-1] - zc[0]))
    half = np.diff(zc) / (np.diff(ph) / np.pi)
    dev = float(np.max(np.abs(half * 2 * f - 1.0))) if half.size else 0.0
    return TrajectoryCheck(int(zc.size), float(f), dev)
