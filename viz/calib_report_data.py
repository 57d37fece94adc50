"""What the calibration report shows, apart from how it is drawn.

:class:`ReportData` and its two adapters (:func:`report_data_from_result`,
:func:`report_data_from_failure`), the verdict and the advice on what to
record next (:func:`verdict`, :func:`record_next`), and the per-detection
residuals recomputed from the recordings (:func:`wall_residuals`,
:func:`inliers`).  The pages themselves are in :mod:`mems_stereo.viz.calib_report`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mems_stereo.calib.association import wall_data
from mems_stereo.calib.checks import first_photon_mean
from mems_stereo.calib.model import PARAM_UNIT, code_time
from mems_stereo.calib.observability import DEFAULT_MAX_STD
from mems_stereo.calib.problem import SPOT_MAX, SPOT_MIN, WallData, shot_model, spot_share
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult
from mems_stereo.viz.calib_report_checks import check_rows

from mems_stereo.model.camera import normalized_coordinates
from mems_stereo.model.scanner import scan_angle_from_phase
from mems_stereo.model.system import System

#: display factor and unit per parameter (SI value × factor)
UNITS = dict(PARAM_UNIT)
#: what to record when a parameter is weak, not observable or trades off
ADVICE = {
    "tdc_offset": "give measured target distances (--target-distances-file) or record "
                  "targets at more distinct distances: the TDC offset trades off with the "
                  "baseline and the target distances otherwise",
    "baseline_z": "give measured target distances, or add a target much nearer or farther "
                  "(the along-axis baseline shows only in how range changes with distance)",
    "baseline_x": "record targets at more distinct distances (e.g. 1.5, 2.5 and 4 m): the "
                  "baseline shows in how disparity changes with distance",
    "theta0": "record targets at more distinct distances; θ0 trades off with the baseline "
              "at a single distance",
    "theta_mech_max": "use targets that fill the whole scan (wider or nearer walls): the "
                      "amplitude shows in the scan's extent",
    "phase_offset": "record more shots per target (the phase shows in the left/right "
                    "asymmetry of the scan)",
    "baseline_y": "a line sensor cannot see baseline_y: measure it mechanically and fix it "
                  "(--fix baseline_y)",
    "fx": "calibrate the receiver's intrinsics on their own (ChArUco, 2-D arrays) or fix fx",
    "cx": "calibrate the receiver's intrinsics on their own (ChArUco, 2-D arrays) or fix cx",
}
#: the advice instead, when the target distances were measured and given already
ADVICE_DISTANCES_GIVEN = {
    "tdc_offset": "record targets at more distinct distances, or measure the target "
                  "distances more precisely (--distance-std): the TDC offset trades off with "
                  "the baseline and the target distances",
    "baseline_z": "add a target much nearer or farther (the along-axis baseline shows only "
                  "in how range changes with distance)",
}
MIN_TARGETS = 3
MIN_DETECTIONS = 30
WEAK_FRACTION = 0.5  # σ above this share of the tolerance: "weak"


@dataclass
class ReportData:
    """Everything the report shows, independent of the calibration's own classes.

    ok : a result exists; reason : why the calibration failed ("" when fine);
    kind : the failure's kind ("input" / "estimate", "" for a result).
    names : estimated parameters; values/std/initial : dict name → SI (a
    failure: what the fit had reached, possibly empty).  correlation : (n, n).
    planes : (T, 3) α, β (rad), D (m); planes_std (T, 3).  walls : per wall
    dict as :attr:`CalibrationResult.targets` (source, distance_axis, mu,
    spot_px, tilt, signal_share, consistency_p, time_shifts, column_shifts …).
    checks : name → (value, limit, passed).  max_std : σ limit per parameter
    (SI) above which it counts as not determined.  header : the filed report's
    header (:func:`~mems_stereo.viz.calib_report_header.report_header`), or None.
    """

    ok: bool
    reason: str
    nominal: System | None
    system: System | None
    kind: str = ""
    names: list = field(default_factory=list)
    values: dict = field(default_factory=dict)
    std: dict = field(default_factory=dict)
    initial: dict = field(default_factory=dict)
    correlation: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    rms: dict = field(default_factory=dict)
    n_detections: int = 0
    fixed: list = field(default_factory=list)
    unobservable: list = field(default_factory=list)
    tradeoffs: list = field(default_factory=list)
    planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    planes_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    walls: list = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    target_names: list = field(default_factory=list)
    max_std: dict = field(default_factory=lambda: dict(DEFAULT_MAX_STD))
    header: dict | None = None


def source_stem(source) -> str:
    return Path(str(source)).stem


def report_data_from_result(result: CalibrationResult, *, nominal: System | None = None,
                            max_std: dict | None = None) -> ReportData:
    """The adapter: a :class:`~mems_stereo.calib.result.CalibrationResult` → :class:`ReportData`.

    nominal : the nominal system (default: the calibrated system with the
    result's ``initial`` values, i.e. the nominal one for every free parameter).
    """
    names = list(result.names)
    if nominal is None:
        nominal = result.system.with_params(**{n: result.initial[n] for n in names})
    n_t = len(result.planes)
    walls = [dict(t) for t in result.targets]
    return ReportData(
        ok=True, reason="", nominal=nominal, system=result.system, names=names,
        values={n: float(result.values[n]) for n in names},
        std={n: float(result.std[n]) for n in names},
        initial={n: float(result.initial[n]) for n in names},
        correlation=np.asarray(result.correlation, dtype=np.float64),
        rms={k: float(v) for k, v in result.rms.items()},
        n_detections=int(result.n_detections), fixed=list(result.fixed),
        unobservable=list(result.unobservable),
        tradeoffs=[(a, b, float(c)) for a, b, c in result.tradeoffs],
        planes=np.asarray(result.planes, dtype=np.float64).reshape(n_t, -1)[:, :3],
        planes_std=np.asarray(result.planes_std, dtype=np.float64).reshape(n_t, -1)[:, :3],
        walls=walls, checks=dict(result.checks), warnings=list(result.warnings),
        target_names=[source_stem(t.get("source", f"wall {j}")) for j, t in enumerate(walls)],
        max_std=dict(DEFAULT_MAX_STD, **(max_std or {})))


def report_data_from_failure(failure, *, nominal: System | None = None,
                             max_std: dict | None = None) -> ReportData:
    """A :class:`~mems_stereo.calib.result.CalibrationFailure` or an exception →
    :class:`ReportData` (``ok`` False; what the fit learnt from ``failure.details``)."""
    if isinstance(failure, CalibrationFailure):
        reason, kind, det = failure.reason, failure.kind, dict(failure.details)
        warns = list(failure.warnings)
    else:
        reason = str(failure) or type(failure).__name__
        kind, det, warns = "exception", {}, []
    values = {k: float(v) for k, v in (det.get("values") or {}).items()}
    std = {k: float(v) for k, v in (det.get("std") or {}).items()}
    initial = {}
    if nominal is not None:
        for n in values:
            try:
                initial[n] = float(nominal.get_param(n))
            except (KeyError, ValueError, AttributeError):
                pass
    wp = np.asarray(det.get("walls") or np.zeros((0, 3)), dtype=np.float64)
    walls = [dict(t) for t in det.get("targets") or []]
    return ReportData(ok=False, reason=reason, kind=kind, nominal=nominal, system=None,
                      names=list(values), values=values, std=std, initial=initial,
                      planes=wp.reshape(len(wp), -1)[:, :3] if wp.size else np.zeros((0, 3)),
                      walls=walls, checks=dict(det.get("checks") or {}), warnings=warns,
                      target_names=[source_stem(t.get("source", f"wall {j}"))
                                    for j, t in enumerate(walls)],
                      max_std=dict(DEFAULT_MAX_STD, **(max_std or {})))


# --------------------------------------------------------------------------- analysis
def verdict(d: ReportData) -> tuple[str, list[str]]:
    """``(headline, lines)`` of the observability verdict and the failed checks."""
    lines = []
    if not d.ok:
        lines.append(f"no calibration: the {d.kind or 'fit'} failed (see Why above)")
        lines += [f"check failed: {r['text']}" for r in checks_of(d) if r["passed"] is False]
        return "FAILED", lines
    weak = []
    for n in d.names:
        tol = d.max_std.get(n, math.inf)
        s = d.std.get(n, math.nan)
        if not math.isfinite(s) or s > tol:
            weak.append(n)
            lines.append(f"{n}: not determined (σ {fmt_param(n, s)} > tolerance "
                         f"{fmt_param(n, tol)})")
        elif s > WEAK_FRACTION * tol:
            weak.append(n)
            lines.append(f"{n}: weak (σ {fmt_param(n, s)}, tolerance {fmt_param(n, tol)})")
    for n in d.unobservable:
        lines.append(f"{n}: not observable from these data (held at nominal)")
    for a, b, c in d.tradeoffs:
        lines.append(f"{a} and {b} trade off (correlation {c:+.3f})")
    failed = [r for r in checks_of(d) if r["passed"] is False]
    for r in failed:
        lines.append(f"check failed: {r['text']}")
    head = "CONVERGED, WEAK" if (weak or failed) else "CONVERGED"
    if not lines:
        lines.append("every estimated parameter is known to better than half its tolerance")
    return head, lines


def checks_of(d: ReportData) -> list[dict]:
    """The checks as rows, measured beside fitted with units
    (:func:`~mems_stereo.viz.calib_report_checks.check_rows`)."""
    return check_rows(d.checks, d.walls, d.nominal, d.system)


def check_text(v) -> str:
    if isinstance(v, (tuple, list)) and len(v) == 3:
        val, lim, ok = v
        def f(x):
            return (f"{x:.4g}" if isinstance(x, (int, float)) else str(x))
        lim_s = (f"{f(lim[0])} … {f(lim[1])}" if isinstance(lim, (tuple, list))
                 else f(lim))
        return f"{f(val)} (limit {lim_s}) {'ok' if ok else 'FAILED'}"
    return str(v)


def record_next(d: ReportData) -> list[str]:
    """What to record next (plain sentences), empty when nothing is weak."""
    todo: list[str] = []
    names = set()
    if not d.ok:
        names |= {n for n in ADVICE if n in d.reason}
    for n in d.names:
        tol = d.max_std.get(n, math.inf)
        s = d.std.get(n, math.nan)
        if d.ok and (not math.isfinite(s) or s > WEAK_FRACTION * tol):
            names.add(n)
    names |= set(d.unobservable)
    names -= set(d.fixed)  # held at a given value already: fixing it again is no advice
    measured = any(t.get("distance_measured") is not None for t in d.walls)
    for n in sorted(names, key=lambda x: list(ADVICE).index(x) if x in ADVICE else 99):
        text = (ADVICE_DISTANCES_GIVEN.get(n, ADVICE.get(n)) if measured else ADVICE.get(n))
        if text is not None and text not in todo:
            todo.append(text)
    n_t = len(d.walls) if d.walls else len(d.planes)
    if 0 < n_t < MIN_TARGETS:
        todo.append(f"record at least {MIN_TARGETS} target distances spanning the working "
                    f"range (found {n_t})")
    for name, t in zip(d.target_names, d.walls):
        share = t.get("signal_share")
        if share is not None and share < 0.5:
            todo.append(f"{name}: the fit explains only {share:.0%} of the returns above "
                        "the background: check that the recording shows one flat wall")
        sig = t.get("signal_expected")
        if sig is not None and sig < MIN_DETECTIONS:
            todo.append(f"{name}: only {sig:.0f} signal detections; record more shots or "
                        "use a brighter target")
    if not d.ok and any(k in d.reason for k in ("no wall", "flat", "return", "converge",
                                                "implausible")):
        todo.append("record a flat, matte wall filling the scan, one wall per recording, "
                    "at several distances (e.g. 1.5, 2.5 and 4 m)")
    if d.ok and d.rms.get("pixel", 0.0) > 0.75:
        todo.append(f"pixel residuals (RMS {d.rms['pixel']:.2f} px) exceed the pixel "
                    f"quantisation and spot size: check the intrinsics and distortion")
    return todo


def fmt_param(name: str, v: float) -> str:
    f, unit = UNITS.get(name, (1.0, ""))
    return f"{v * f:.4g} {unit}".strip() if math.isfinite(v) else "—"


@dataclass(frozen=True, slots=True)
class WallResiduals:
    """The detections of one wall recording near its predicted return, and their
    residuals under the calibrated model (M detections; receiver camera frame).

    theta : (M,) float64, scan angle, rad.
    pixel : (M,) float64, the fired column.
    res_pixel : (M,) float64, column − predicted column, px.
    res_time : (M,) float64, TDC time − the model's prediction, s: the expected
        first signal photon (pulse centre + σ · first-photon shift) when the
        wall's fitted signal is known, else the pulse centre (path/c + TDC offset).
    points : (M, 3) float64, m: the detections triangulated (camera ray ∩ scan beam).
    first_photon : the first-photon shift was removed from ``res_time``.
    """

    theta: np.ndarray
    pixel: np.ndarray
    res_pixel: np.ndarray
    res_time: np.ndarray
    points: np.ndarray
    first_photon: bool = False


def _first_photon_shift(target: dict | None, pred: np.ndarray, cols, rows,
                        two_d: bool) -> np.ndarray | None:
    """(M,) s: what the model predicts beyond the pulse centre for each detection,
    σ · :func:`~mems_stereo.calib.checks.first_photon_mean` of the pixel's mean
    signal m = μ · g / g_ref · spot share; None without the wall's fitted signal."""
    keys = ("mu", "spot_px", "log_gref", "pulse_sigma")
    if not target or any(target.get(k) is None for k in keys):
        return None
    sigma = float(target["pulse_sigma"])
    s_px = min(max(float(target["spot_px"]), SPOT_MIN), SPOT_MAX)
    share = spot_share(cols, pred[:, 1], s_px)[0]
    if two_d:
        share = share * spot_share(rows, pred[:, 2], s_px)[0]
    m = float(target["mu"]) * np.exp(pred[:, 3] - float(target["log_gref"])) * share
    return sigma * first_photon_mean(m, -pred[:, 0] / sigma)


def wall_residuals(system: System, wall, plane, radius: int = 3,
                   window: float = 40e-9, target: dict | None = None) -> WallResiduals:
    """Residuals of one wall recording under the calibrated model.

    wall : :class:`~mems_stereo.calib.problem.WallData` (or a Recording, reduced
    with :func:`~mems_stereo.calib.association.wall_data`).  plane : (α, β, D)
    of the wall (rad, rad, m).  Every fired pixel within ``radius`` columns of
    a shot's predicted image and within ``window`` of its predicted time counts.
    target : the wall's entry of the result's ``targets`` (``mu``, ``spot_px``,
    ``log_gref``, ``pulse_sigma``): the time residuals then have the
    first-photon shift the fit models removed (the first of several signal
    photons arrives before the pulse centre: −5 ns at 10 photons per shot for
    a 15 ns pulse); without it they are against the pulse centre.

    Returns the detections and their residuals (:class:`WallResiduals`).
    """
    w = wall if isinstance(wall, WallData) else wall_data(wall)
    K, H, W = w.bins.shape
    wall5 = np.array([plane[0], plane[1], plane[2], 0.0, 0.0], dtype=np.float64)
    pred, ok = shot_model(system, {}, wall5, w.phase)
    shots = np.flatnonzero(ok)
    u = pred[shots, 1]
    row = (np.clip(np.rint(pred[shots, 2]), 0, H - 1).astype(np.int64) if H > 1
           else np.zeros(shots.size, np.int64))
    off = np.arange(-radius, radius + 1)
    cols = np.rint(u)[:, None] + off[None, :]
    sh = np.broadcast_to(shots[:, None], cols.shape)
    rr = np.broadcast_to(row[:, None], cols.shape)
    inside = (cols >= 0) & (cols < W)
    sh, cols, rr = sh[inside], cols[inside].astype(np.int64), rr[inside]
    code = w.bins[sh, rr, cols]
    t = code_time(code, w.bin_width)
    keep = (code > 0) & (np.abs(t - pred[sh, 0]) < window)
    sh, cols, rr, t = sh[keep], cols[keep], rr[keep], t[keep]
    p = pred[sh]
    shift = _first_photon_shift(target, p, cols.astype(np.float64), rr.astype(np.float64),
                                H > 1)
    theta = scan_angle_from_phase(w.phase[sh], system.scanner)
    return WallResiduals(theta=theta, pixel=cols.astype(np.float64),
                         res_pixel=cols - p[:, 1],
                         res_time=t - p[:, 0] - (0.0 if shift is None else shift),
                         points=_triangulate(system, cols.astype(np.float64),
                                             rr.astype(np.float64), theta),
                         first_photon=shift is not None)


def _triangulate(system: System, col, row, theta) -> np.ndarray:
    """(M, 3) m: camera ray of pixel (col, row) ∩ scan beam at angle θ, in x–z."""
    m = col.size
    pts = np.full((m, 3), np.nan)
    if not m:
        return pts
    xy = normalized_coordinates(np.stack([col, row], axis=1),
                                system.receiver.camera_matrix, system.receiver.dist_coeffs)
    sc = system.scanner
    e1, e2 = np.asarray(sc.normal_basis, dtype=np.float64)
    dl = np.asarray(sc.laser_direction, dtype=np.float64)
    nm = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    d = dl - 2.0 * (nm @ dl)[:, None] * nm
    p = np.asarray(sc.position, dtype=np.float64)
    # t·x_n − s·d_x = p_x ; t − s·d_z = p_z
    det = -d[:, 0] + xy[:, 0] * d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-p[0] * d[:, 2] + p[2] * d[:, 0]) / -det
    pts = np.stack([t * xy[:, 0], t * xy[:, 1], t], axis=1)
    pts[~(np.isfinite(t) & (t > 0))] = np.nan
    return pts


def inliers(r: WallResiduals, k: float = 5.0) -> np.ndarray:
    """Detections within ``k`` robust σ (1.4826·MAD) of the median in both residuals.

    The window around the predicted return also holds background detections
    and returns of neighbouring pixels; the fit's likelihood weighs them
    against the background, the report draws them apart (grey).
    """
    ok = np.isfinite(r.res_pixel) & np.isfinite(r.res_time)
    for v, floor in ((r.res_pixel, 0.5), (r.res_time, 1e-10)):  # px, s
        if ok.sum() < 3:
            return ok
        med = np.median(v[ok])
        mad = 1.4826 * np.median(np.abs(v[ok] - med))
        ok &= np.abs(v - med) <= k * max(mad, floor)
    return ok
