"""The calibration report: a PDF a calibration engineer files with the hardware.

:func:`write_calibration_report` renders, with matplotlib's ``PdfPages`` (Agg,
no display), for a :class:`~mems_stereo.calib.result.CalibrationResult`:

1. the verdict, the estimates with σ against the nominal values, RMS
   residuals, the per-wall values, the observability verdict and the
   plausibility checks, and **what to record next** when something is weak;
2. the estimates' shift from nominal in units of their σ, and the correlation
   matrix of the estimates;
3. the residuals of every wall against scan angle and against pixel.  The
   result carries no per-detection residuals, so they are recomputed here
   from the recordings (when given) with the calibrated system and the fitted
   planes: pixel residual = fired column − the beam's predicted image (px),
   time residual = TDC time − modelled return centre (ns; includes the
   first-photon bias the fit models).  Without recordings this page shows
   what the result carries instead (per-wall consistency shifts per quarter of
   the sensor) and says so;
4. the fitted planes seen from above (x–z, receiver camera frame), with the
   detections triangulated (camera ray ∩ scan beam) when recordings are given,
   and the scanner and receiver drawn at their positions.

A :class:`~mems_stereo.calib.result.CalibrationFailure` (or an exception)
renders two pages: why (the reason, and what to record), and what the fit
learnt before it stopped (checks, partial estimates, per-wall values) with the
TDC-time histogram of each recording when recordings are given.

Everything the pages use goes through two adapters,
:func:`report_data_from_result` and :func:`report_data_from_failure`, so that a
change of the calibration result's shape is absorbed there.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mems_stereo.calib.model import PARAM_UNIT
from mems_stereo.calib.observability import DEFAULT_MAX_STD
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult

from mems_stereo.errors import FormatError
from mems_stereo.model.system import System
from mems_stereo.util.atomic import atomic_output

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
    (SI) above which it counts as not determined.
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


def _stem(source) -> str:
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
        target_names=[_stem(t.get("source", f"wall {j}")) for j, t in enumerate(walls)],
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
                      target_names=[_stem(t.get("source", f"wall {j}"))
                                    for j, t in enumerate(walls)],
                      max_std=dict(DEFAULT_MAX_STD, **(max_std or {})))


# --------------------------------------------------------------------------- analysis
def verdict(d: ReportData) -> tuple[str, list[str]]:
    """``(headline, lines)`` of the observability verdict and the failed checks."""
    lines = []
    if not d.ok:
        lines.append(f"no calibration: the {d.kind or 'fit'} failed (see Why above)")
        lines += [f"check failed: {k}: {_check_value(v)}" for k, v in d.checks.items()
                  if _passed(v) is False]
        return "FAILED", lines
    weak = []
    for n in d.names:
        tol = d.max_std.get(n, math.inf)
        s = d.std.get(n, math.nan)
        if not math.isfinite(s) or s > tol:
            weak.append(n)
            lines.append(f"{n}: not determined (σ {_fmt(n, s)} > tolerance {_fmt(n, tol)})")
        elif s > WEAK_FRACTION * tol:
            weak.append(n)
            lines.append(f"{n}: weak (σ {_fmt(n, s)}, tolerance {_fmt(n, tol)})")
    for n in d.unobservable:
        lines.append(f"{n}: not observable from these data (held at nominal)")
    for a, b, c in d.tradeoffs:
        lines.append(f"{a} and {b} trade off (correlation {c:+.3f})")
    failed = [k for k, v in d.checks.items() if _passed(v) is False]
    for k in failed:
        lines.append(f"check failed: {k}: {_check_value(d.checks[k])}")
    head = "CONVERGED, WEAK" if (weak or failed) else "CONVERGED"
    if not lines:
        lines.append("every estimated parameter is known to better than half its tolerance")
    return head, lines


def _passed(v):
    if isinstance(v, (tuple, list)) and len(v) == 3:
        return bool(v[2])
    return None


def _check_value(v) -> str:
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
    for n in sorted(names, key=lambda x: list(ADVICE).index(x) if x in ADVICE else 99):
        if n in ADVICE and ADVICE[n] not in todo:
            todo.append(ADVICE[n])
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


def _fmt(name: str, v: float) -> str:
    f, unit = UNITS.get(name, (1.0, ""))
    return f"{v * f:.4g} {unit}".strip() if math.isfinite(v) else "—"


def wall_residuals(system: System, wall, plane, radius: int = 3,
                   window: float = 40e-9) -> dict:
    """Residuals of one wall recording under the calibrated model.

    wall : :class:`~mems_stereo.calib.problem.WallData` (or a Recording, reduced
    with :func:`~mems_stereo.calib.association.wall_data`).  plane : (α, β, D)
    of the wall (rad, rad, m).  Every fired pixel within ``radius`` columns of
    a shot's predicted image and within ``window`` of its predicted time counts.

    Returns a dict of (M,) float64 arrays: ``theta`` scan angle (rad),
    ``pixel`` column, ``res_pixel`` column − predicted column (px),
    ``res_time`` TDC time − (path/c + tdc offset) (s), and ``points`` (M, 3) m,
    the detections triangulated (camera ray ∩ scan beam), receiver camera frame.
    """
    from mems_stereo.calib.association import wall_data
    from mems_stereo.calib.model import beam_hits, code_time, plane_normal
    from mems_stereo.calib.problem import WallData

    from mems_stereo.model.scanner import scan_angle_from_phase

    w = wall if isinstance(wall, WallData) else wall_data(wall)
    K, H, W = w.bins.shape
    hits = beam_hits(system, {}, w.phase, plane_normal(plane[0], plane[1]), float(plane[2]))
    tau = hits.path / system.speed_of_light + system.tdc.offset
    ok = hits.ok & np.isfinite(hits.pixel[:, 0])
    shots = np.flatnonzero(ok)
    u = hits.pixel[shots, 0]
    row = (np.clip(np.rint(hits.pixel[shots, 1]), 0, H - 1).astype(np.int64) if H > 1
           else np.zeros(shots.size, np.int64))
    off = np.arange(-radius, radius + 1)
    cols = np.rint(u)[:, None] + off[None, :]
    sh = np.broadcast_to(shots[:, None], cols.shape)
    rr = np.broadcast_to(row[:, None], cols.shape)
    inside = (cols >= 0) & (cols < W)
    sh, cols, rr = sh[inside], cols[inside].astype(np.int64), rr[inside]
    code = w.bins[sh, rr, cols]
    t = code_time(code, w.bin_width)
    uu = hits.pixel[sh, 0]
    keep = (code > 0) & (np.abs(t - tau[sh]) < window)
    sh, cols, rr, t, uu = sh[keep], cols[keep], rr[keep], t[keep], uu[keep]
    theta = scan_angle_from_phase(w.phase[sh], system.scanner)
    return {"theta": theta, "pixel": cols.astype(np.float64),
            "res_pixel": cols - uu, "res_time": t - tau[sh],
            "points": _triangulate(system, cols.astype(np.float64), rr.astype(np.float64),
                                   theta)}


def _triangulate(system: System, col, row, theta) -> np.ndarray:
    """(M, 3) m: camera ray of pixel (col, row) ∩ scan beam at angle θ, in x–z."""
    from mems_stereo.model.camera import normalized_coordinates

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


def inliers(r: dict, k: float = 5.0) -> np.ndarray:
    """Detections within ``k`` robust σ (1.4826·MAD) of the median in both residuals.

    The window around the predicted return also holds background detections
    and returns of neighbouring pixels; the fit's likelihood weighs them
    against the background, the report draws them apart (grey).
    """
    ok = np.isfinite(r["res_pixel"]) & np.isfinite(r["res_time"])
    for key in ("res_pixel", "res_time"):
        v = r[key]
        if ok.sum() < 3:
            return ok
        med = np.median(v[ok])
        mad = 1.4826 * np.median(np.abs(v[ok] - med))
        floor = 0.5 if key == "res_pixel" else 1e-10
        ok &= np.abs(v - med) <= k * max(mad, floor)
    return ok


# --------------------------------------------------------------------------- pages
def _text_page(pdf, title: str, blocks: list[tuple[str, list[str]]], color: str = "k",
               bottom: float = 0.04):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.27, 11.69))
    fig.text(0.06, 0.96, title, fontsize=15, weight="bold", va="top", color=color)
    y = 0.92
    for head, lines in blocks:
        if y < bottom + 0.02:
            break
        fig.text(0.06, y, head, fontsize=11, weight="bold", va="top")
        y -= 0.024
        for line in lines:
            for part in _wrap(line, 95):
                if y < bottom:
                    break
                fig.text(0.08, y, part, fontsize=8.5, family="monospace", va="top")
                y -= 0.017
        y -= 0.012
    if pdf is not None:
        pdf.savefig(fig)
    return fig


def _wrap(s: str, n: int) -> list[str]:
    import textwrap

    return textwrap.wrap(s, n, subsequent_indent="    ") or [""]


def _wall_rows(d: ReportData) -> list[str]:
    rows = []
    for j, t in enumerate(d.walls):
        nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
        parts = []
        if "distance_axis" in t:
            s = t.get("distance_axis_std")
            parts.append(f"distance (optical axis) {t['distance_axis']:.4f} m"
                         + (f" ± {s * 1e3:.2f} mm" if s is not None else ""))
        if j < len(d.planes):
            a = d.planes[j, 0]
            sa = (f" ± {d.planes_std[j, 0] * 1e3:.2f}" if j < len(d.planes_std) else "")
            parts.append(f"tilt α {a * 1e3:.1f}{sa} mrad")
        if "mu" in t:
            parts.append(f"{t['mu']:.3g} photons/shot")
        if "spot_px" in t:
            parts.append(f"spot σ {t['spot_px']:.2f} px")
        if "signal_share" in t:
            parts.append(f"signal explained {t['signal_share']:.0%}")
        if "consistency_p" in t:
            parts.append(f"flat-wall consistency p {t['consistency_p']:.2g}")
        if "distance_measured" in t:
            parts.append(f"measured {t['distance_measured']:.4f} m "
                         f"(pull {t.get('distance_pull', math.nan):+.1f}σ)")
        rows.append(f"{nm}: " + ", ".join(parts))
    return rows


def _summary_page(pdf, d: ReportData):
    head, vlines = verdict(d)
    color = {"CONVERGED": "darkgreen", "CONVERGED, WEAK": "darkorange"}.get(head, "darkred")
    blocks = []
    if d.ok:
        rows = [f"{'parameter':<15}{'nominal':>12}{'estimate':>12}{'σ':>10}{'Δ/σ':>8}  unit"]
        for n in d.names:
            f, unit = UNITS.get(n, (1.0, ""))
            s = d.std[n]
            z = (d.values[n] - d.initial[n]) / s if s > 0 and math.isfinite(s) else math.nan
            rows.append(f"{n:<15}{d.initial[n] * f:>12.4f}{d.values[n] * f:>12.4f}"
                        f"{s * f:>10.4f}{z:>8.1f}  {unit}")
        if d.fixed:
            rows.append("fixed at nominal: " + ", ".join(d.fixed))
        blocks.append(("Estimates (σ from the fit's covariance)", rows))
        blocks.append(("Residuals", [f"RMS (signal-weighted) pixel "
                                     f"{d.rms.get('pixel', math.nan):.3f} px, time "
                                     f"{d.rms.get('time', math.nan) * 1e9:.3f} ns, "
                                     f"{d.n_detections} signal detections explained"]))
        blocks.append(("Walls (fitted planes)", _wall_rows(d)))
    else:
        blocks.append(("Why", [f"calibration failed ({d.kind}): {d.reason}"]))
        blocks.append(("Consequence", ["no calibrated system was written: do not use these "
                                       "recordings' estimates (details on the next page)"]))
    blocks.append((f"Observability and checks: {head}", vlines))
    if d.ok and d.checks:
        blocks.append(("Plausibility checks", [f"{k}: {_check_value(v)}"
                                               for k, v in d.checks.items()]))
    if d.warnings:
        blocks.append(("Warnings", list(d.warnings)))
    todo = record_next(d)
    blocks.append(("What to record next", todo or ["nothing: the data determine every "
                                                   "estimated parameter"]))
    _text_page(pdf, f"Calibration report — {head}", blocks, color)


def _failure_page(pdf, d: ReportData, hists: list):
    """Page 2 of a failure: what the fit learnt, and each recording's TDC times."""
    blocks = []
    if d.values:
        rows = [f"{'parameter':<15}{'nominal':>12}{'reached':>12}{'σ':>10}  unit"]
        for n in d.names:
            f, unit = UNITS.get(n, (1.0, ""))
            nom = d.initial.get(n, math.nan)
            s = d.std.get(n, math.nan)
            s_txt = f"{s * f:>10.4f}" if math.isfinite(s) else f"{'—':>10}"
            rows.append(f"{n:<15}{nom * f:>12.4f}{d.values[n] * f:>12.4f}{s_txt}  {unit}")
        blocks.append(("Where the fit stopped (not a calibration)", rows))
    else:
        blocks.append(("Where the fit stopped", ["no estimates: the calibration stopped "
                                                 "before a fit (the recordings cannot "
                                                 "calibrate)" if d.kind == "input" else
                                                 "no estimates were reached"]))
    if d.walls:
        blocks.append(("Walls as fitted", _wall_rows(d)))
    if d.checks:
        blocks.append(("Checks", [f"{k}: {_check_value(v)}" for k, v in d.checks.items()]))
    if d.warnings:
        blocks.append(("Warnings", list(d.warnings)))
    fig = _text_page(None, "Why the calibration failed — details", blocks, "darkred",
                     bottom=0.5 if hists else 0.04)
    if hists:
        ax = fig.add_axes([0.1, 0.07, 0.85, 0.36])
        for j, (name, t) in enumerate(hists):
            if t.size:
                ax.hist(t * 1e9, bins=200, histtype="step", color=f"C{j % 10}",
                        label=f"{name} ({t.size} detections)")
        ax.set_xlabel("TDC time (ns)")
        ax.set_ylabel("detections per bin")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title("detection times of each recording: a flat wall gives one sharp peak "
                     "above the flat background", fontsize=9)
    pdf.savefig(fig)


def _estimates_page(pdf, d: ReportData):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
    a, b = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.2]})
    n = len(d.names)
    z = np.array([(d.values[k] - d.initial[k]) / d.std[k] if d.std[k] > 0 else np.nan
                  for k in d.names])
    y = np.arange(n)
    a.axvspan(-3, 3, color="0.92")
    a.errorbar(z, y, xerr=np.ones(n), fmt="o", color="tab:blue", capsize=3)
    a.axvline(0, color="k", lw=0.8)
    a.set_yticks(y, [f"{k}\n{_fmt(k, d.values[k] - d.initial[k])} ± {_fmt(k, d.std[k])}"
                     for k in d.names], fontsize=8)
    a.invert_yaxis()
    a.set_xlabel("(estimate − nominal) / σ   (bars: ±1σ, band: ±3σ)")
    a.set_title("estimates against nominal")
    C = d.correlation if d.correlation.shape == (n, n) else np.full((n, n), np.nan)
    im = b.imshow(C, vmin=-1, vmax=1, cmap="RdBu_r")
    b.set_xticks(y, d.names, rotation=45, ha="right", fontsize=8)
    b.set_yticks(y, d.names, fontsize=8)
    for i in range(n):
        for j in range(n):
            if np.isfinite(C[i, j]):
                b.text(j, i, f"{C[i, j]:+.2f}", ha="center", va="center", fontsize=7,
                       color="w" if abs(C[i, j]) > 0.6 else "k")
    fig.colorbar(im, ax=b, shrink=0.8, label="correlation")
    b.set_title("correlation of the estimates")
    fig.tight_layout()
    pdf.savefig(fig)


def _residual_page(pdf, d: ReportData, res: list):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
    if not res:  # what the result carries: per-wall shifts per quarter of the sensor
        ax = fig.subplots(1, 2)
        for j, t in enumerate(d.walls):
            nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
            for a, key, f in ((ax[0], "column_shifts", 1.0), (ax[1], "time_shifts", 1e9)):
                v = np.asarray(t.get(key, []), dtype=np.float64) * f
                a.plot(np.arange(v.size) + 1, v, "o-", color=f"C{j % 10}", label=nm)
        ax[0].set_ylabel("column shift (px)")
        ax[1].set_ylabel("TDC-time shift (ns)")
        for a in ax:
            a.axhline(0, color="k", lw=0.8)
            a.set_xlabel("quarter of the sensor (left → right)")
            a.grid(alpha=0.3)
        ax[0].legend(fontsize=8)
        fig.suptitle("no recordings given: per-detection residuals against scan angle and "
                     "pixel need them (--report with the recordings).\nShown instead: what "
                     "the result carries, each wall's consistency shifts per quarter of the "
                     "sensor (a flat wall: all near 0)", fontsize=10)
        pdf.savefig(fig)
        return
    ax = fig.subplots(2, 2)
    lim = {"res_pixel": [0.0, 0.0], "res_time": [0.0, 0.0]}
    n_out = 0
    for j, r in enumerate(res):
        if r is None:
            continue
        nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
        ok = inliers(r)
        n_out += int((~ok).sum())
        for key, f, row in (("res_pixel", 1.0, 0), ("res_time", 1e9, 1)):
            v = r[key] * f
            if ok.any():
                lo, hi = np.percentile(v[ok], [0.5, 99.5])
                lim[key] = [min(lim[key][0], lo), max(lim[key][1], hi)]
            for col, x in enumerate((r["theta"] * 1e3, r["pixel"])):
                a = ax[row, col]
                a.scatter(x[~ok], v[~ok], s=1, color="0.75")
                a.scatter(x[ok], v[ok], s=2, alpha=0.5, color=f"C{j % 10}",
                          label=f"{nm} ({int(ok.sum())} inliers)")
    for row, key in ((0, "res_pixel"), (1, "res_time")):
        lo, hi = lim[key]
        pad = 0.3 * (hi - lo) + 1e-9
        for a in ax[row]:
            a.set_ylim(lo - pad, hi + pad)
    for a in ax.ravel():
        a.axhline(0, color="k", lw=0.8)
        a.grid(alpha=0.3)
    ax[0, 0].set_ylabel("pixel residual (px)")
    ax[1, 0].set_ylabel("time residual (ns)")
    ax[1, 0].set_xlabel("scan angle θ (mrad)")
    ax[1, 1].set_xlabel("pixel (column)")
    ax[0, 0].legend(markerscale=4, fontsize=8)
    fig.suptitle("residuals of every wall, recomputed from the recordings with the calibrated "
                 "system (time: TDC time − modelled return centre, includes the first-photon "
                 f"bias);\ngrey: {n_out} fired pixels near the beam beyond 5 robust σ "
                 "(background, neighbours; off-scale ones not shown)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    pdf.savefig(fig)


def _planes_page(pdf, d: ReportData, res: list, system: System):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
    ax = fig.subplots()
    zmax = 1.0
    pos = np.asarray(system.scanner.position)
    xs = [0.0, float(pos[0])]
    for j in range(max(len(d.planes), len(res))):
        nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
        r = res[j] if j < len(res) else None
        x = None
        if r is not None:
            p = r["points"]
            ok = np.isfinite(p[:, 0]) & inliers(r)
            ax.scatter(p[ok, 0], p[ok, 2], s=3, alpha=0.4, color=f"C{j % 10}", label=nm)
            if ok.any():
                zmax = max(zmax, float(np.nanpercentile(p[ok, 2], 99.5)))
                xs += [float(np.min(p[ok, 0])), float(np.max(p[ok, 0]))]
                x = np.linspace(np.percentile(p[ok, 0], 1), np.percentile(p[ok, 0], 99), 50)
        if j < len(d.planes):
            a_, b_, D = d.planes[j]
            if x is None:  # no detections: the plane across the scan's width at its depth
                z0 = D / (math.cos(a_) * math.cos(b_))
                half = z0 * math.tan(float(system.scanner.theta_mech_max) * 2.0)
                x = np.linspace(-half, half, 50)
                zmax = max(zmax, z0 * 1.1)
                xs += [-half, half]
            zline = (D - x * math.sin(a_) * math.cos(b_)) / (math.cos(a_) * math.cos(b_))
            ax.plot(x, zline, color=f"C{j % 10}" if r is None else "k", lw=1.5, ls="--",
                    zorder=5, label=(f"fitted plane: {nm}" if r is None else
                                          "fitted plane" if j == 0 else None))
    ax.plot([0], [0], "k^", ms=10, label="receiver (projection centre)")
    ax.plot([pos[0]], [pos[2]], "rs", ms=9, label="scanner (mirror pivot)")
    ax.set_xlabel("x (m, receiver camera frame)")
    ax.set_ylabel("z (m, optical axis)")
    ax.set_ylim(-0.1 * zmax, 1.1 * zmax)
    ax.set_xlim(min(xs) - 0.1, max(xs) + 0.1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("walls from above: fitted planes (dashed)"
                 + (", detections triangulated with the calibrated system" if res else
                    "; no recordings given, so no detections drawn"))
    pdf.savefig(fig)


def _time_histograms(walls) -> list:
    out = []
    for w in walls:
        codes = w.bins[w.bins > 0]
        out.append((_stem(w.source), (codes.astype(np.float64) - 0.5) * w.bin_width))
    return out


def write_calibration_report(result, path: str | os.PathLike, *, recordings=None,
                             targets=None, nominal: System | None = None,
                             max_std: dict | None = None) -> Path:
    """Render the calibration report (PDF) of a result or of a failed calibration.

    Parameters
    ----------
    result : a :class:`~mems_stereo.calib.result.CalibrationResult` (4 pages), a
        :class:`~mems_stereo.calib.result.CalibrationFailure` or an exception
        (2 pages: why, and what the fit learnt), or a ready :class:`ReportData`.
    path : output ``.pdf`` (written atomically).
    recordings : the calibration's recordings (Recordings or FORMAT v1 paths),
        for the residual and top-view pages (and a failure's TDC-time
        histograms); matched to the result's walls by source name.
    targets : the same already reduced (:class:`~mems_stereo.calib.problem.WallData`),
        instead of ``recordings``.
    nominal : the nominal system (a failure's "nominal" column).
    max_std : σ limits (SI) per parameter, as given to the fit.

    Returns the path.  Raises FormatError when ``path`` is not a ``.pdf``.
    """
    from matplotlib.backends.backend_pdf import PdfPages

    p = Path(path)
    if p.suffix.lower() != ".pdf":
        raise FormatError(f"expected a .pdf file name, found {p.name!r}", str(p))
    if isinstance(result, ReportData):
        d = result
    elif isinstance(result, (CalibrationFailure, BaseException)):
        d = report_data_from_failure(result, nominal=nominal, max_std=max_std)
    else:
        d = report_data_from_result(result, nominal=nominal, max_std=max_std)
    walls = None
    if targets is not None:
        walls = list(targets)
    elif recordings is not None:
        from mems_stereo.calib.association import wall_data

        from mems_stereo.io.recording import Recording, read_recording

        walls = []
        for r in recordings:
            rec = r if isinstance(r, Recording) else read_recording(r, truth=False)
            try:
                walls.append(wall_data(rec))
            except FormatError:  # no known phase: nothing to draw for it
                continue
    with atomic_output(p) as tmp, PdfPages(str(tmp)) as pdf:
        _summary_page(pdf, d)
        if d.ok:
            res = []
            if walls:
                by_name = {_stem(w.source): w for w in walls}
                for j, nm in enumerate(d.target_names):
                    w = by_name.get(nm)
                    res.append(None if w is None or j >= len(d.planes)
                               else wall_residuals(d.system, w, d.planes[j]))
                if all(r is None for r in res):
                    res = []
            if d.names:
                _estimates_page(pdf, d)
            _residual_page(pdf, d, res)
            _planes_page(pdf, d, res, d.system)
        else:
            _failure_page(pdf, d, _time_histograms(walls) if walls else [])
        info = pdf.infodict()
        info["Title"] = "mems-stereo calibration report"
        info["Subject"] = verdict(d)[0]
    return p
