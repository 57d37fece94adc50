"""The calibration report: a PDF a calibration engineer files with the hardware.

:func:`write_calibration_report` renders, with matplotlib's ``PdfPages`` (Agg,
no display):

1. the verdict (converged / not converged / failed, and why), the estimates
   with σ against the nominal values, RMS residuals, detections per target,
   the observability verdict and **what to record next** when something is weak;
2. the estimates' shift from nominal in units of their σ, and the correlation
   matrix;
3. the residuals of every target against scan angle and against pixel
   (pixel residual in px; time residual = TDC time − modelled return centre,
   ns, which includes the first-photon bias the fit models);
4. the fitted planes seen from above (x–z, receiver camera frame) with the
   detections triangulated (camera ray ∩ scan beam) and the scanner and
   receiver drawn at their positions.

A failed calibration (an exception such as
:class:`~mems_stereo.errors.NotObservableError`, or a result that did not
converge) still renders: the first page says why and what to record, and the
detections are drawn with the nominal system.

Everything the pages use goes through one adapter, :func:`report_data_from_result`
(CalibrationResult → :class:`ReportData`), so that a change of the calibration
result's shape is absorbed in one function.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.model.system import System
from mems_stereo.util.atomic import atomic_output

#: display factor and unit per parameter (SI value × factor)
UNITS = {"theta0": (1e3, "mrad"), "theta_mech_max": (1e3, "mrad"),
         "phase_offset": (1e3, "mrad"), "tdc_offset": (1e9, "ns"),
         "baseline_x": (1e3, "mm"), "baseline_y": (1e3, "mm"), "baseline_z": (1e3, "mm"),
         "fx": (1.0, "px"), "cx": (1.0, "px")}
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

    ok : a result exists (possibly not converged); reason : why it failed or
    did not converge ("" when fine).  names : estimated parameters;
    values/std/initial : dict name → SI.  correlation : (n, n).  planes :
    (T, 3) α, β (rad), D (m); planes_std (T, 3).  targets : list of
    :class:`~mems_stereo.calib.detections.TargetDetections` (or None).
    max_std : tolerance per parameter (SI).
    """

    ok: bool
    converged: bool
    reason: str
    nominal: System | None
    system: System | None
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
    targets: list | None = None
    target_names: list = field(default_factory=list)
    max_std: dict = field(default_factory=dict)


def _max_std() -> dict:
    from mems_stereo.calib.fit import DEFAULT_MAX_STD

    return dict(DEFAULT_MAX_STD)


def report_data_from_result(result, *, targets=None, nominal: System | None = None,
                            target_names=None) -> ReportData:
    """The adapter: a :class:`~mems_stereo.calib.fit.CalibrationResult` → :class:`ReportData`.

    The only function that reads the calibration result; re-point it when the
    result's fields change.
    """
    names = list(result.names)
    if nominal is None:
        nominal = result.system.with_params(**{n: result.initial[n] for n in names})
    n_t = len(result.planes)
    return ReportData(
        ok=True, converged=bool(result.converged),
        reason="" if result.converged else (result.message or "the fit did not converge"),
        nominal=nominal, system=result.system, names=names,
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
        targets=targets,
        target_names=list(target_names) if target_names else [f"target {j}"
                                                               for j in range(n_t)],
        max_std=_max_std())


def report_data_from_failure(error, *, nominal: System | None = None, targets=None,
                             target_names=None) -> ReportData:
    """A failed calibration (an exception or a message) → :class:`ReportData`."""
    reason = str(error) if str(error) else type(error).__name__
    n_t = len(targets) if targets is not None else 0
    return ReportData(ok=False, converged=False, reason=reason, nominal=nominal, system=None,
                      targets=targets,
                      target_names=list(target_names) if target_names else
                      [f"target {j}" for j in range(n_t)], max_std=_max_std())


def detections_for_report(recordings, system: System, confidence: float = 0.997):
    """Signal detections of each recording classified with ``system`` (as calibration does).

    ``recordings`` : Recordings or FORMAT v1 paths.  Returns a list of
    :class:`~mems_stereo.calib.detections.TargetDetections`.
    """
    from mems_stereo.calib.detections import detections_from_labels

    from mems_stereo.io.recording import Recording, read_recording
    from mems_stereo.model.scanner import phase_from_zero_crossings, scan_angle_from_phase
    from mems_stereo.pipeline.intervals import interval_table
    from mems_stereo.pipeline.pass1 import classify_and_accumulate

    table = interval_table(system, confidence)
    out = []
    for r in recordings:
        rec = r if isinstance(r, Recording) else read_recording(r, truth=False)
        ph, ok = phase_from_zero_crossings(rec.shot_time, rec.zero_crossings, rec.rising)
        theta = scan_angle_from_phase(ph, system.scanner)
        labels = classify_and_accumulate(rec.bins, np.where(ok, theta, 0.0), ok, table,
                                         system.tdc.n_bins)[0]
        out.append(detections_from_labels(ph, ok, rec.bins, labels, source=rec.source))
    return out


# --------------------------------------------------------------------------- analysis
def verdict(d: ReportData) -> tuple[str, list[str]]:
    """``(headline, lines)`` of the observability verdict."""
    if not d.ok:
        return "FAILED", ["no estimates: the calibration stopped (see Why above)"]
    lines = []
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
    if not d.converged:
        head = "NOT CONVERGED"
    elif weak:
        head = "CONVERGED, WEAK"
    else:
        head = "CONVERGED"
    if not lines:
        lines.append("every estimated parameter is known to better than half its tolerance")
    return head, lines


def record_next(d: ReportData) -> list[str]:
    """What to record next (plain sentences), empty when nothing is weak."""
    todo: list[str] = []
    names = set()
    if not d.ok:
        names |= {n for n in ADVICE if n in d.reason}
    for n in d.names:
        tol = d.max_std.get(n, math.inf)
        s = d.std.get(n, math.nan)
        if not math.isfinite(s) or s > WEAK_FRACTION * tol:
            names.add(n)
    names |= set(d.unobservable)
    for n in sorted(names, key=lambda x: list(ADVICE).index(x) if x in ADVICE else 99):
        if n in ADVICE and ADVICE[n] not in todo:
            todo.append(ADVICE[n])
    n_t = len(d.targets) if d.targets is not None else len(d.planes)
    if 0 < n_t < MIN_TARGETS:
        todo.append(f"record at least {MIN_TARGETS} target distances spanning the working "
                    f"range (found {n_t})")
    if d.targets is not None:
        for name, t in zip(d.target_names, d.targets):
            if t.n_detections < MIN_DETECTIONS:
                todo.append(f"{name}: only {t.n_detections} signal detections; record more "
                            f"shots or use a brighter target")
    if d.ok and d.rms.get("pixel", 0.0) > 0.5:
        todo.append(f"pixel residuals (RMS {d.rms['pixel']:.2f} px) exceed the pixel "
                    f"quantisation (0.29 px): check the intrinsics and distortion")
    return todo


def _fmt(name: str, v: float) -> str:
    f, unit = UNITS.get(name, (1.0, ""))
    return f"{v * f:.4g} {unit}".strip() if math.isfinite(v) else "—"


def target_residuals(system: System, target, plane) -> dict:
    """Per detection of one target: scan angle θ (rad), pixel, pixel residual (px),
    time residual (s), and the triangulated point (M, 3) m, receiver camera frame.

    ``plane`` : (α, β, D) of the target in the calibrated model (or None:
    residuals NaN, points still triangulated).
    """
    from mems_stereo.calib.model import beam_hits, code_time, plane_normal

    from mems_stereo.model.camera import normalized_coordinates
    from mems_stereo.model.scanner import scan_angle_from_phase

    phase = np.asarray(target.phase)[target.shot]
    theta = scan_angle_from_phase(phase, system.scanner)
    col = np.asarray(target.column, dtype=np.float64)
    m = col.size
    res_pix = np.full(m, np.nan)
    res_t = np.full(m, np.nan)
    if plane is not None and m:
        n = plane_normal(plane[0], plane[1])
        hits = beam_hits(system, {}, phase, n, float(plane[2]))
        res_pix = col - hits.pixel[:, 0]
        res_t = (code_time(target.code, system.tdc.bin_width)
                 - (hits.path / system.speed_of_light + system.tdc.offset))
    # triangulate in the x–z plane: camera ray t·(x_n, 1) = scanner p + s·d
    pts = np.full((m, 3), np.nan)
    if m:
        xy = normalized_coordinates(np.stack([col, np.asarray(target.row, float)], axis=1),
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
    return {"theta": theta, "pixel": col, "res_pixel": res_pix, "res_time": res_t,
            "points": pts}


def inliers(r: dict, k: float = 5.0) -> np.ndarray:
    """Detections within ``k`` robust σ (1.4826·MAD) of the median in both residuals.

    Signal-labelled detections include returns of a neighbouring pixel and
    background that passed the consistency test; the fit's robust loss
    down-weights them, the report draws them apart (grey).
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
def _text_page(pdf, title: str, blocks: list[tuple[str, list[str]]], color: str = "k"):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.27, 11.69))
    fig.text(0.06, 0.96, title, fontsize=15, weight="bold", va="top", color=color)
    y = 0.92
    for head, lines in blocks:
        if y < 0.06:
            break
        fig.text(0.06, y, head, fontsize=11, weight="bold", va="top")
        y -= 0.024
        for line in lines:
            for part in _wrap(line, 95):
                if y < 0.04:
                    break
                fig.text(0.08, y, part, fontsize=8.5, family="monospace", va="top")
                y -= 0.017
        y -= 0.012
    pdf.savefig(fig)


def _wrap(s: str, n: int) -> list[str]:
    import textwrap

    return textwrap.wrap(s, n, subsequent_indent="    ") or [""]


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
        blocks.append(("Residuals", [f"RMS pixel {d.rms.get('pixel', math.nan):.3f} px, "
                                     f"time {d.rms.get('time', math.nan) * 1e9:.3f} ns, "
                                     f"{d.n_detections} signal detections"]))
        trows = []
        for j, (p, s) in enumerate(zip(d.planes, d.planes_std)):
            nm = d.target_names[j] if j < len(d.target_names) else f"target {j}"
            nd = (f", {d.targets[j].n_detections} detections"
                  if d.targets is not None and j < len(d.targets) else "")
            trows.append(f"{nm}: plane D {p[2]:.4f} m ± {s[2] * 1e3:.2f} mm, tilt "
                         f"{p[0] * 1e3:.2f} ± {s[0] * 1e3:.2f} mrad{nd}")
        blocks.append(("Targets", trows))
    else:
        blocks.append(("Why", _wrap(d.reason, 95)))
        if d.targets is not None:
            blocks.append(("Data", [f"{nm}: {t.n_detections} signal detections "
                                    f"(classified with the nominal system)"
                                    for nm, t in zip(d.target_names, d.targets)]))
    blocks.append((f"Observability: {head}", vlines))
    todo = record_next(d)
    blocks.append(("What to record next", todo or ["nothing: the data determine every "
                                                   "estimated parameter"]))
    _text_page(pdf, f"Calibration report — {head}", blocks, color)


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
    ax = fig.subplots(2, 2)
    lim = {"res_pixel": [0.0, 0.0], "res_time": [0.0, 0.0]}
    n_out = 0
    for j, r in enumerate(res):
        nm = d.target_names[j] if j < len(d.target_names) else f"target {j}"
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
    fig.suptitle("residuals of every target (time: TDC time − modelled return centre, "
                 f"includes the first-photon bias); grey: {n_out} detections beyond 5 robust "
                 "σ (off-scale ones not shown)", fontsize=10)
    fig.tight_layout()
    pdf.savefig(fig)


def _planes_page(pdf, d: ReportData, res: list, system: System):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
    ax = fig.subplots()
    zmax = 1.0
    xs = [0.0, float(system.scanner.position[0])]
    for j, r in enumerate(res):
        nm = d.target_names[j] if j < len(d.target_names) else f"target {j}"
        p = r["points"]
        ok = np.isfinite(p[:, 0])
        if d.ok:
            ok &= inliers(r)
        else:  # no residuals without a fit: drop the far tails of the triangulation
            if ok.sum() > 10:
                lo, hi = np.percentile(p[ok, 2], [2, 98])
                ok &= (p[:, 2] >= lo) & (p[:, 2] <= hi)
        ax.scatter(p[ok, 0], p[ok, 2], s=3, alpha=0.4, color=f"C{j % 10}", label=nm)
        if ok.any():
            zmax = max(zmax, float(np.nanpercentile(p[ok, 2], 99.5)))
            xs += [float(np.min(p[ok, 0])), float(np.max(p[ok, 0]))]
            x = np.linspace(np.nanpercentile(p[ok, 0], 1), np.nanpercentile(p[ok, 0], 99), 50)
            if j < len(d.planes):
                a_, b_, D = d.planes[j]
                zline = (D - x * math.sin(a_) * math.cos(b_)) / (math.cos(a_) * math.cos(b_))
                ax.plot(x, zline, color="k", lw=1.5, ls="--", zorder=5,
                        label="fitted plane" if j == 0 else None)
    pos = np.asarray(system.scanner.position)
    ax.plot([0], [0], "k^", ms=10, label="receiver (projection centre)")
    ax.plot([pos[0]], [pos[2]], "rs", ms=9, label="scanner (mirror pivot)")
    ax.set_xlabel("x (m, receiver camera frame)")
    ax.set_ylabel("z (m, optical axis)")
    ax.set_ylim(-0.1 * zmax, 1.1 * zmax)
    ax.set_xlim(min(xs) - 0.1, max(xs) + 0.1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("targets from above: detections triangulated with the "
                 + ("calibrated" if d.ok else "nominal") + " system"
                 + (", lines: fitted planes" if d.ok else ""))
    pdf.savefig(fig)


def write_calibration_report(result, path: str | os.PathLike, *, targets=None,
                             recordings=None, nominal: System | None = None,
                             target_names=None, confidence: float = 0.997) -> Path:
    """Render the calibration report (PDF) of a result or of a failed calibration.

    Parameters
    ----------
    result : a :class:`~mems_stereo.calib.fit.CalibrationResult`, an exception
        (the calibration failed; its message is the reason), or a ready
        :class:`ReportData`.
    path : output ``.pdf`` (written atomically).
    targets : the fit's TargetDetections, for the residual and top-view pages;
        or ``recordings`` (Recordings or paths) to classify them here with the
        calibrated system (the nominal one when the calibration failed).
    nominal : the nominal system (needed for a failure with recordings).
    target_names : one label per target (default "target j").

    Hook for ``mems-stereo calibrate … --report REPORT.pdf``: call it with the
    result and the recording paths; on failure call it in the ``except``
    with the exception and ``nominal=``, then still exit non-zero.
    """
    from matplotlib.backends.backend_pdf import PdfPages

    p = Path(path)
    if p.suffix.lower() != ".pdf":
        raise FormatError(f"expected a .pdf file name, found {p.name!r}", str(p))
    if isinstance(result, ReportData):
        d = result
    elif isinstance(result, BaseException):
        d = report_data_from_failure(result, nominal=nominal, targets=targets,
                                     target_names=target_names)
    else:
        d = report_data_from_result(result, targets=targets, nominal=nominal,
                                    target_names=target_names)
    draw_system = d.system if d.ok else d.nominal
    if d.targets is None and recordings is not None and draw_system is not None:
        d.targets = detections_for_report(recordings, draw_system, confidence)
        if not d.target_names or len(d.target_names) != len(d.targets):
            d.target_names = [Path(str(getattr(r, "source", r))).stem for r in recordings]
    res = []
    if d.targets is not None and draw_system is not None:
        for j, t in enumerate(d.targets):
            plane = d.planes[j] if d.ok and j < len(d.planes) else None
            res.append(target_residuals(draw_system, t, plane))
    with atomic_output(p) as tmp, PdfPages(str(tmp)) as pdf:
        _summary_page(pdf, d)
        if d.ok and d.names:
            _estimates_page(pdf, d)
        if res and d.ok:
            _residual_page(pdf, d, res)
        if res:
            _planes_page(pdf, d, res, draw_system)
        info = pdf.infodict()
        info["Title"] = "mems-stereo calibration report"
        info["Subject"] = verdict(d)[0]
    return p
