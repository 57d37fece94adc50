"""Outcome of a calibration: :class:`CalibrationResult` (a system with σ, covariance,
residuals, fitted planes and the observability verdict) or
:class:`CalibrationFailure` (why not; tests false and hands out no system,
as scikit-image's ``RANSAC`` returns a failed model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from mems_stereo.calib.model import PARAM_UNIT

from mems_stereo.model.system import System


@dataclass
class CalibrationResult:
    """A calibration that passed every check (OpenCV-style: values, σ, RMS).

    Attributes
    ----------
    system : the calibrated System (with its ``calibration`` block).
    names : free system parameters, order of ``covariance``.
    values, std, initial : dict name → SI value, its σ, and the nominal value.
    covariance : (n, n) SI units over ``names``; correlation : (n, n).
    rms : {"pixel": px, "time": s} RMS of the signal-weighted residuals.
    n_detections : expected signal detections explained by the fit.
    fixed : parameters held at their given value; unobservable : parameters
        the data cannot determine (held at their given value).
    tradeoffs : [(a, b, correlation)] for ``|correlation| > 0.9``.
    planes : (T, 3) α (rad), β (rad), D (m) of each wall; planes_std : (T, 3).
    targets : per wall dict (source, distance along the optical axis and σ,
        signal photons per shot, spot σ, consistency pulls, signal share).
    checks : dict name → (value, limit, passed) of the plausibility checks.
    converged : always True for a result (a failed fit is a CalibrationFailure).
    """

    system: System
    names: list
    values: dict
    std: dict
    initial: dict
    covariance: np.ndarray
    correlation: np.ndarray
    rms: dict
    n_detections: int
    fixed: list
    unobservable: list
    tradeoffs: list
    planes: np.ndarray
    planes_std: np.ndarray
    targets: list = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    converged: bool = True
    message: str = ""
    report: str = ""
    iterations: int = 0
    elapsed: float = 0.0
    extra: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return True

    @property
    def rms_pixel(self) -> float:
        return float(self.rms["pixel"])

    @property
    def rms_time(self) -> float:
        return float(self.rms["time"])

    def calibration_dict(self) -> dict:
        """The ``calibration`` object written into the system JSON."""
        params = {n: {"value": self.values[n],
                      "std": self.std[n] if math.isfinite(self.std[n]) else None,
                      "initial": self.initial[n]} for n in self.names}
        corr = {f"{a}/{b}": round(float(r), 6) for a, b, r in self.tradeoffs}
        return {"parameters": params, "rms_pixel": self.rms_pixel, "rms_time": self.rms_time,
                "n_detections": int(self.n_detections), "fixed": list(self.fixed),
                "unobservable": list(self.unobservable), "correlations": corr,
                "converged": True,
                "covariance": {"names": list(self.names),
                               "matrix": [[float(v) for v in row] for row in self.covariance]},
                "targets": [{"source": t["source"], "alpha": float(p[0]), "beta": float(p[1]),
                             "distance": float(p[2]), "std": [float(s) for s in ps],
                             "distance_axis": float(t["distance_axis"]),
                             "distance_axis_std": float(t["distance_axis_std"])}
                            for p, ps, t in zip(self.planes, self.planes_std, self.targets)]}

    def to_dict(self) -> dict:
        """Everything as JSON-able values (for ``--report``)."""
        return {"ok": True, "calibration": self.calibration_dict(),
                "targets": _jsonable(self.targets), "checks": _jsonable(self.checks),
                "warnings": list(self.warnings), "elapsed_s": self.elapsed,
                "correlation": _jsonable(self.correlation),
                "labels": self.extra.get("labels", []),
                "correlation_full": _jsonable(self.extra.get("correlation_full"))}


@dataclass
class CalibrationFailure:
    """A calibration that must not be used: ``bool(failure)`` is False and it has no
    ``system``.

    Attributes
    ----------
    reason : one line saying why (what was found, what to do).
    kind : "input" (the recordings cannot calibrate: no wall return, not flat
        walls, nothing to observe) or "estimate" (the fit did not converge, or
        its result failed a plausibility check).
    details : whatever the fit learnt (estimates so far, checks, per-wall
        values) for a diagnostic report.
    """

    reason: str
    kind: str = "estimate"
    details: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    elapsed: float = 0.0
    converged: bool = False

    def __bool__(self) -> bool:
        return False

    @property
    def system(self):
        raise AttributeError(f"a failed calibration has no system: {self.reason}")

    @property
    def message(self) -> str:
        return self.reason

    @property
    def report(self) -> str:
        lines = [f"calibration FAILED ({self.kind}): {self.reason}"]
        lines += [f"  warning: {w}" for w in self.warnings]
        for k, v in self.details.get("checks", {}).items():
            lines.append(f"  check {k}: {v}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"ok": False, "kind": self.kind, "reason": self.reason,
                "warnings": list(self.warnings), "elapsed_s": self.elapsed,
                "details": _jsonable(self.details)}


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, (np.integer, np.bool_)):
        return v.item()
    return v


def format_report(r: CalibrationResult) -> str:
    """Plain-text table of estimates, σ, RMS, walls, checks and trade-offs."""
    lines = [f"calibration: converged, {len(r.planes)} wall(s), "
             f"{r.n_detections} signal detections, {r.elapsed:.1f} s",
             f"  RMS residual (signal-weighted): pixel {r.rms_pixel:.3f} px, "
             f"time {r.rms_time * 1e9:.3f} ns",
             f"  {'parameter':<16}{'nominal':>14}{'estimate':>14}{'σ':>12}  unit"]
    for n in r.names:
        f, unit = PARAM_UNIT[n]
        lines.append(f"  {n:<16}{r.initial[n] * f:>14.4f}{r.values[n] * f:>14.4f}"
                     f"{r.std[n] * f:>12.4f}  {unit}")
    for j, (p, s, t) in enumerate(zip(r.planes, r.planes_std, r.targets)):
        lines.append(f"  wall {j} ({t['source']}): distance along the optical axis "
                     f"{t['distance_axis']:.4f} ± {t['distance_axis_std']:.4f} m, "
                     f"tilt {p[0] * 1e3:.1f} ± {s[0] * 1e3:.2f} mrad, "
                     f"{t['mu']:.3g} photons/shot, spot σ {t['spot_px']:.2f} px")
    if r.fixed:
        lines.append("  fixed: " + ", ".join(r.fixed))
    if r.unobservable:
        lines.append("  not observable from these data: " + ", ".join(r.unobservable)
                     + " (held at the nominal value)")
    for a, b, c in r.tradeoffs:
        lines.append(f"  {a} and {b} trade off: correlation {c:+.4f}")
    for w in r.warnings:
        lines.append(f"  warning: {w}")
    return "\n".join(lines)
