"""The two-axis MEMS mirror: second axis, gimbal reflection model, angles of both axes.

A version-1 system describes one mirror axis (``scanner``, the *fast* axis,
resonant, with its zero-crossing monitor).  The optional object
``scanner.axis2`` adds a second axis (``docs/two_axis.md``):

* ``mode: "resonant"`` (Lissajous): θ2(t) = theta0 + theta_mech_max · cos(φ2(t) +
  phase_offset), φ2 from the axis' own zero crossings (recorded under
  ``/scanner/axis2/zero_crossings``, ``/scanner/axis2/rising``), the same law
  as the fast axis (:mod:`mems_stereo.model.scanner`);
* ``mode: "quasistatic"`` (raster): θ2(t) = theta0 + θ2_mech(t), where the
  recording's position channel (``/scanner/axis2/time``,
  ``/scanner/axis2/position``, rad mechanical) is interpolated linearly; the
  system's ``f_mech``, ``theta_mech_max`` and ``phase_offset`` describe the
  nominal triangle wave θ2_mech(t) = theta_mech_max · tri(2π f_mech t + phase_offset)
  (used by the simulator and for planning, never by processing).

Reflection model (gimbal).  With ``[e1, e2] = scanner.normal_basis`` and the
fast (inner) axis ``a1 = e1 × e2``, the version-1 normal is
``n1(θ1) = cos θ1 · e1 + sin θ1 · e2 = R(a1, θ1) e1``.  The second axis ``a2``
(``axis2.axis``, a unit vector of the world frame, perpendicular to a1) turns it:

* ``gimbal: "outer2"`` (default; axis 2 is the outer frame, fixed to the
  housing, axis 1 rides on it): ``n = R(a2, θ2) · R(a1, θ1) · e1``;
* ``gimbal: "outer1"`` (axis 1 is the outer frame): ``n = R(a1, θ1) · R(a2, θ2) · e1``.

``R(a, α)`` is the right-handed rotation about ``a`` by α (Rodrigues).
With θ2 ≡ 0 both give the version-1 normal exactly.  Mechanical coupling
between the axes: ``coupling`` κ (rad/rad, default 0) adds κ · θ1_mech to the
second axis' angle (θ2_eff = θ2 + κ · (θ1 − θ0_1)).  The scan direction follows
the reflection law ``d = d_laser − 2 (n·d_laser) n`` (paper Eq. 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mems_stereo.errors import FormatError, GeometryError
from mems_stereo.model.hardware import Scanner, System
from mems_stereo.model.scanner import phase_from_zero_crossings, reflect, scan_angle_from_phase
from mems_stereo.util.jsonfile import FieldChecker

MODES = ("resonant", "quasistatic")
GIMBALS = ("outer2", "outer1")


@dataclass(frozen=True)
class Axis2:
    """The second mirror axis (``scanner.axis2`` of the system JSON).

    Attributes
    ----------
    mode : "resonant" (Lissajous) or "quasistatic" (raster slow axis).
    axis : (3,) float64 unit vector, world frame, perpendicular to a1 = e1 × e2.
    theta0 : rad, rest angle of axis 2.
    f_mech : Hz, nominal frequency (resonance, or the triangle's repetition rate).
    theta_mech_max : rad, mechanical amplitude.
    phase_offset : rad, delay of the true phase behind the monitor (resonant),
        or the nominal triangle's phase (quasistatic).
    gimbal : "outer2" or "outer1" (which axis is the outer frame).
    coupling : rad/rad, share of θ1_mech added to θ2 (mechanical crosstalk).
    """

    mode: str
    axis: np.ndarray
    theta0: float
    f_mech: float
    theta_mech_max: float
    phase_offset: float = 0.0
    gimbal: str = "outer2"
    coupling: float = 0.0


def axis2_from_dict(d: Any, scanner: Scanner, source: str = "<dict>") -> Axis2:
    """Validate ``scanner.axis2`` against the (already validated) fast axis."""
    ctx = FieldChecker(source)
    fld = "scanner.axis2"
    if not isinstance(d, dict):
        raise ctx.fail(fld, f"expected an object, found {type(d).__name__}")
    mode = ctx.req(d, "mode", fld)
    if mode not in MODES:
        raise ctx.fail(f"{fld}.mode", f"expected one of {list(MODES)}, found {mode!r}")
    gimbal = d.get("gimbal", "outer2")
    if gimbal not in GIMBALS:
        raise ctx.fail(f"{fld}.gimbal", f"expected one of {list(GIMBALS)}, found {gimbal!r}")
    a2 = ctx.array(ctx.req(d, "axis", fld), f"{fld}.axis", (3,))
    n = float(np.linalg.norm(a2))
    if abs(n - 1.0) > 1e-6:
        raise ctx.fail(f"{fld}.axis", f"expected a unit vector, found norm {n:.9g}")
    a1 = fast_axis(scanner)
    dot = float(a1 @ a2)
    if abs(dot) > 1e-6:
        raise ctx.fail(f"{fld}.axis", f"expected a vector perpendicular to the fast axis "
                                      f"e1 x e2 = {a1.tolist()}, found a1·a2 = {dot:.6g}")
    return Axis2(
        mode=mode, axis=a2,
        theta0=ctx.number(ctx.req(d, "theta0", fld), f"{fld}.theta0"),
        f_mech=ctx.number(ctx.req(d, "f_mech", fld), f"{fld}.f_mech", positive=True),
        theta_mech_max=ctx.number(ctx.req(d, "theta_mech_max", fld), f"{fld}.theta_mech_max",
                                  positive=True),
        phase_offset=ctx.number(d.get("phase_offset", 0.0), f"{fld}.phase_offset"),
        gimbal=gimbal,
        coupling=ctx.number(d.get("coupling", 0.0), f"{fld}.coupling"),
    )


def axis2_to_dict(a: Axis2) -> dict:
    """The JSON object of an :class:`Axis2`."""
    return {"mode": a.mode, "axis": np.asarray(a.axis, float).tolist(),
            "theta0": float(a.theta0), "f_mech": float(a.f_mech),
            "theta_mech_max": float(a.theta_mech_max), "phase_offset": float(a.phase_offset),
            "gimbal": a.gimbal, "coupling": float(a.coupling)}


def is_two_axis(system: System) -> bool:
    """True when the system's scanner has a second axis."""
    return system.scanner.axis2 is not None


def require_two_axis(system: System, what: str = "system") -> Axis2:
    a = system.scanner.axis2
    if a is None:
        raise FormatError("expected a two-axis scanner (scanner.axis2), found a one-axis one",
                          what, "scanner.axis2")
    return a


# --------------------------------------------------------------------------
# reflection model


def fast_axis(scanner: Scanner) -> np.ndarray:
    """a1 = e1 × e2, (3,) float64 unit: the fast (version-1) rotation axis."""
    B = np.asarray(scanner.normal_basis, dtype=np.float64)
    return np.cross(B[0], B[1])


def rotate(v, axis, angle) -> np.ndarray:
    """Rodrigues rotation of vectors ``v`` (..., 3) about unit ``axis`` (3,) or (..., 3)
    by ``angle`` (...) rad (right-handed).  Returns (..., 3) float64."""
    v = np.asarray(v, dtype=np.float64)
    k = np.asarray(axis, dtype=np.float64)
    a = np.asarray(angle, dtype=np.float64)[..., None]
    kv = np.cross(np.broadcast_to(k, v.shape), v)
    kdv = np.sum(k * v, axis=-1, keepdims=True)
    return v * np.cos(a) + kv * np.sin(a) + k * kdv * (1.0 - np.cos(a))


def effective_theta2(theta1, theta2, scanner: Scanner) -> np.ndarray:
    """θ2 plus the mechanical coupling κ · (θ1 − θ0_1), rad."""
    a2 = scanner.axis2
    return np.asarray(theta2, float) + a2.coupling * (np.asarray(theta1, float) - scanner.theta0)


def mirror_normal_2d(theta1, theta2, scanner: Scanner) -> np.ndarray:
    """Unit mirror normal n(θ1, θ2), (..., 3) float64, world frame (gimbal model above)."""
    a2 = require_two_axis_scanner(scanner)
    B = np.asarray(scanner.normal_basis, dtype=np.float64)
    a1 = fast_axis(scanner)
    t1, t2 = np.broadcast_arrays(np.asarray(theta1, float),
                                 effective_theta2(theta1, theta2, scanner))
    e1 = np.broadcast_to(B[0], t1.shape + (3,))
    if a2.gimbal == "outer2":
        n1 = np.cos(t1)[..., None] * B[0] + np.sin(t1)[..., None] * B[1]
        return rotate(n1, a2.axis, t2)
    return rotate(rotate(e1, a2.axis, t2), a1, t1)


def require_two_axis_scanner(scanner: Scanner) -> Axis2:
    a2 = scanner.axis2
    if a2 is None:
        raise GeometryError("scanner.axis2: expected a two-axis scanner, found none")
    return a2


def scan_direction_2d(theta1, theta2, scanner: Scanner) -> np.ndarray:
    """Unit scan direction d(θ1, θ2), (..., 3) float64, world frame (paper Eq. 6)."""
    d = np.asarray(scanner.laser_direction, dtype=np.float64)
    return reflect(d, mirror_normal_2d(theta1, theta2, scanner))


def scan_direction_2d_jacobian(theta1, theta2, scanner: Scanner, step: float = 1e-7):
    """∂d/∂θ1 and ∂d/∂θ2 (each (..., 3), per rad), by central differences.

    Differences of :func:`scan_direction_2d` (smooth; truncation error
    ~ step² ≈ 1e-14); coupling included through :func:`effective_theta2`.
    """
    t1 = np.asarray(theta1, float)
    t2 = np.asarray(theta2, float)
    g1 = (scan_direction_2d(t1 + step, t2, scanner)
          - scan_direction_2d(t1 - step, t2, scanner)) / (2 * step)
    g2 = (scan_direction_2d(t1, t2 + step, scanner)
          - scan_direction_2d(t1, t2 - step, scanner)) / (2 * step)
    return g1, g2


# --------------------------------------------------------------------------
# angles from the monitors


def validate_position_channel(times, position, source: str = "",
                              field: str = "/scanner/axis2/time"):
    """Check a slow-axis position channel: (P,) increasing finite times and (P,) finite rad."""
    t = np.asarray(times, dtype=np.float64)
    p = np.asarray(position, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise FormatError(f"expected a 1-D array of at least 2 times, found shape {t.shape}",
                          source, field)
    if p.shape != t.shape:
        raise FormatError(f"expected shape {t.shape} like the times, found {p.shape}", source,
                          field.rsplit("/", 1)[0] + "/position")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise FormatError("expected finite values, found NaN or inf", source, field)
    if np.any(np.diff(t) <= 0):
        raise FormatError("expected strictly increasing times", source, field)
    return t, p


@dataclass(frozen=True)
class Axis2Monitor:
    """What the recording holds for axis 2: zero crossings (resonant) or a
    position channel (quasistatic).  Arrays (Z,) or (P,) float64."""

    zero_crossings: np.ndarray | None = None
    rising: np.ndarray | None = None
    time: np.ndarray | None = None
    position: np.ndarray | None = None


def scan_angles_2d(times, zero_crossings, rising, monitor2: Axis2Monitor, scanner: Scanner):
    """θ1, θ2 of every shot from the recorded monitors.

    Parameters
    ----------
    times : (K,) float64 s, shot trigger times.
    zero_crossings, rising : the fast axis' monitor (FORMAT v1).
    monitor2 : :class:`Axis2Monitor` of axis 2.
    scanner : the two-axis scanner.

    Returns
    -------
    theta1, theta2 : (K,) float64 rad; NaN where a shot lies outside either
        monitor's span (never extrapolated).  θ2 here is the axis' own angle;
        the coupling enters in the reflection model.
    valid : (K,) bool.
    """
    a2 = require_two_axis_scanner(scanner)
    t = np.asarray(times, dtype=np.float64)
    # the fast axis with its hardware model (harmonics, monitor edges; docs/hardware.md)
    ph1, v1 = phase_from_zero_crossings(t, zero_crossings, rising, scanner)
    th1 = scan_angle_from_phase(ph1, scanner)
    if a2.mode == "resonant":
        if monitor2.zero_crossings is None:
            raise FormatError("expected zero crossings of the resonant axis 2, found none",
                              field="/scanner/axis2/zero_crossings")
        ph2, v2 = phase_from_zero_crossings(t, monitor2.zero_crossings, monitor2.rising)
        th2 = a2.theta0 + a2.theta_mech_max * np.cos(ph2 + a2.phase_offset)
    else:
        if monitor2.time is None:
            raise FormatError("expected the position channel of the quasistatic axis 2, "
                              "found none", field="/scanner/axis2/position")
        pt, pp = validate_position_channel(monitor2.time, monitor2.position)
        v2 = (t >= pt[0]) & (t <= pt[-1])
        th2 = np.full(t.shape, np.nan)
        th2[v2] = a2.theta0 + np.interp(t[v2], pt, pp)
    valid = v1 & v2
    return np.where(valid, th1, np.nan), np.where(valid, th2, np.nan), valid


def triangle_wave(phase) -> np.ndarray:
    """tri(φ): period 2π, +1 at φ ≡ 0, −1 at φ ≡ π, linear in between."""
    x = np.mod(np.asarray(phase, float), 2 * np.pi) / np.pi  # [0, 2)
    return np.where(x < 1.0, 1.0 - 2.0 * x, 2.0 * x - 3.0)
