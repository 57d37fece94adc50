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

What the pages show (the data, the verdict, the residuals) is computed in
:mod:`mems_stereo.viz.calib_report_data`; everything goes through two adapters,
:func:`report_data_from_result` and :func:`report_data_from_failure`, so that a
change of the calibration result's shape is absorbed there.
"""

from __future__ import annotations

import json
import math
import os
import textwrap
from pathlib import Path

import numpy as np
from mems_stereo.calib.result import CalibrationFailure
from mems_stereo.viz.calib_report_data import (  # noqa: F401  (public names re-exported)
    ADVICE,
    UNITS,
    ReportData,
    WallResiduals,
    check_text,
    checks_of,
    fmt_param,
    inliers,
    record_next,
    report_data_from_failure,
    report_data_from_result,
    source_stem,
    verdict,
    wall_residuals,
)
from mems_stereo.viz.calib_report_header import header_lines
from mems_stereo.viz.calib_report_json import (
    load_walls,
    report_dict,
    report_residuals,
)

from mems_stereo.errors import FormatError
from mems_stereo.model.system import System
from mems_stereo.util.atomic import atomic_output, atomic_write_text

#: pulls beyond this many σ are drawn at the axis' edge, marked (the estimates page)
PULL_AXIS = 5.0


# --------------------------------------------------------------------------- pages
def _text_page(pdf, title: str, blocks: list[tuple[str, list[str]]], color: str = "k",
               bottom: float = 0.04):
    """Text blocks on A4 pages; with ``pdf`` what does not fit continues on further
    pages ("title (continued)"), without it the one figure is returned (cut at ``bottom``)."""
    from matplotlib.figure import Figure

    def page(head: str):
        f = Figure(figsize=(8.27, 11.69))
        f.text(0.06, 0.96, head, fontsize=15, weight="bold", va="top", color=color)
        return f

    fig = page(title)
    y = 0.92
    for head, lines in blocks:
        parts = [p for line in lines for p in _wrap(line, 95)]
        if y - 0.024 - 0.017 * min(len(parts), 3) < bottom and pdf is not None:
            pdf.savefig(fig)
            fig, y = page(f"{title} (continued)"), 0.92
        fig.text(0.06, y, head, fontsize=11, weight="bold", va="top")
        y -= 0.024
        for part in parts:
            if y < bottom:
                if pdf is None:
                    break
                pdf.savefig(fig)
                fig, y = page(f"{title} (continued)"), 0.92
            fig.text(0.08, y, part, fontsize=8.5, family="monospace", va="top")
            y -= 0.017
        y -= 0.012
    if pdf is not None:
        pdf.savefig(fig)
    return fig


def _wrap(s: str, n: int) -> list[str]:
    return textwrap.wrap(s, n, subsequent_indent="    ") or [""]


def _wall_rows(d: ReportData) -> list[str]:
    rows = []
    for j, t in enumerate(d.walls):
        nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
        parts = []
        if "distance_axis" in t:
            s = t.get("distance_axis_std")
            parts.append(f"distance (optical axis) {t['distance_axis']:.4f}"
                         + (f" ± {s:.4f}" if s is not None else "") + " m")
        if j < len(d.planes):
            a = d.planes[j, 0]
            sa = (f" ± {d.planes_std[j, 0] * 1e3:.2f}" if j < len(d.planes_std) else "")
            parts.append(f"tilt α {a * 1e3:.1f}{sa} mrad")
        if "mu" in t:
            parts.append(f"{t['mu']:.3g} photons/shot")
        if "spot_px" in t:
            parts.append(f"spot σ {t['spot_px']:.2f} px")
        if "signal_share" in t:  # of a Poisson excess over the background: at most 100 %
            parts.append(f"signal explained {min(t['signal_share'], 1.0):.0%}")
        if "consistency_p" in t:
            parts.append(f"flat-wall consistency p {t['consistency_p']:.2g}")
        if "distance_measured" in t:
            pull = t.get("distance_pull")
            parts.append(f"measured {t['distance_measured']:.4f} m"
                         + (f" (pull {pull:+.1f}σ)" if pull is not None else ""))
        if t.get("time_residual_mean") is not None:
            parts.append(f"time residual mean {t['time_residual_mean'] * 1e9:+.3f} ns")
        rows.append(f"{nm}: " + ", ".join(parts))
    return rows


def _summary_page(pdf, d: ReportData):
    head, vlines = verdict(d)
    color = {"CONVERGED": "darkgreen", "CONVERGED, WEAK": "darkorange"}.get(head, "darkred")
    blocks = []
    if d.header:
        blocks.append(("Record", header_lines(d.header)))
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
        blocks.append(("Residuals (after what the model predicts, the first-photon shift "
                       "included)", [f"RMS (signal-weighted) pixel "
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
        blocks.append(("Plausibility checks (measured beside fitted)",
                       [r["text"] for r in checks_of(d)]))
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
        blocks.append(("Checks (measured beside fitted)", [r["text"] for r in checks_of(d)]))
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
    inside = np.abs(z) <= PULL_AXIS
    a.errorbar(z[inside], y[inside], xerr=np.ones(int(inside.sum())), fmt="o",
               color="tab:blue", capsize=3)
    for k in np.flatnonzero(np.isfinite(z) & ~inside):  # clipped to the axis, marked
        edge = math.copysign(PULL_AXIS, z[k])
        a.plot([edge], [y[k]], ">" if z[k] > 0 else "<", color="tab:red", ms=9)
        a.annotate(f"{z[k]:+.0f}σ", (edge, y[k]), textcoords="offset points",
                   xytext=(-8 if z[k] > 0 else 8, 7), ha="right" if z[k] > 0 else "left",
                   fontsize=7, color="tab:red")
    a.set_xlim(-PULL_AXIS - 0.5, PULL_AXIS + 0.5)
    a.axvline(0, color="k", lw=0.8)
    a.set_yticks(y, [f"{k}\n{fmt_param(k, d.values[k] - d.initial[k])} ± {fmt_param(k, d.std[k])}"
                     for k in d.names], fontsize=8)
    a.invert_yaxis()
    a.set_xlabel(f"(estimate − nominal) / σ   (bars: ±1σ, band: ±3σ; beyond ±{PULL_AXIS:.0f}σ: "
                 "red marks at the edge)")
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


def _shift_page(pdf, d: ReportData):
    """Without the recordings: what the result carries, each wall's consistency shifts
    per quarter of the sensor."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11.69, 8.27))
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


def _residual_page(pdf, d: ReportData, res: list):
    """Every wall's pixel and time residuals against scan angle and pixel (the
    recordings' detections, ``res``); without them :func:`_shift_page`."""
    from matplotlib.figure import Figure

    if not res:
        _shift_page(pdf, d)
        return
    fig = Figure(figsize=(11.69, 8.27))
    ax = fig.subplots(2, 2)
    lim = {"res_pixel": [0.0, 0.0], "res_time": [0.0, 0.0]}
    n_out = 0
    for j, r in enumerate(res):
        if r is None:
            continue
        nm = d.target_names[j] if j < len(d.target_names) else f"wall {j}"
        ok = inliers(r)
        n_out += int((~ok).sum())
        for key, resid, f, row in (("res_pixel", r.res_pixel, 1.0, 0),
                                   ("res_time", r.res_time, 1e9, 1)):
            v = resid * f
            if ok.any():
                lo, hi = np.percentile(v[ok], [0.5, 99.5])
                lim[key] = [min(lim[key][0], lo), max(lim[key][1], hi)]
            for col, x in enumerate((r.theta * 1e3, r.pixel)):
                a = ax[row, col]
                a.scatter(x[~ok], v[~ok], s=1, color="0.75", rasterized=True)
                mean = float(np.mean(v[ok])) if ok.any() else math.nan
                unit = "px" if row == 0 else "ns"
                a.scatter(x[ok], v[ok], s=2, alpha=0.5, color=f"C{j % 10}", rasterized=True,
                          label=f"{nm} ({int(ok.sum())} inliers, mean {mean:+.3f} {unit})")
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
    ax[1, 0].legend(markerscale=4, fontsize=8)
    fp = all(r.first_photon for r in res if r is not None)
    fig.suptitle("residuals of every wall, recomputed from the recordings with the calibrated "
                 "system (time: TDC time − the model's "
                 + ("expected first photon, pulse centre + first-photon shift" if fp else
                    "pulse centre; the first-photon shift is not removed")
                 + f");\ngrey: {n_out} fired pixels near the beam beyond 5 robust σ "
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
            p = r.points
            ok = np.isfinite(p[:, 0]) & inliers(r)
            ax.scatter(p[ok, 0], p[ok, 2], s=3, alpha=0.4, color=f"C{j % 10}", label=nm,
                       rasterized=True)
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
        out.append((source_stem(w.source), (codes.astype(np.float64) - 0.5) * w.bin_width))
    return out


def report_data(result, *, nominal: System | None = None, max_std: dict | None = None,
                header: dict | None = None) -> ReportData:
    """The :class:`ReportData` of a result, a failure, an exception or a ReportData,
    with ``header`` (:func:`~mems_stereo.viz.calib_report_header.report_header`) set."""
    if isinstance(result, ReportData):
        d = result
    elif isinstance(result, (CalibrationFailure, BaseException)):
        d = report_data_from_failure(result, nominal=nominal, max_std=max_std)
    else:
        d = report_data_from_result(result, nominal=nominal, max_std=max_std)
    if header is not None:
        d.header = header
    return d


def write_calibration_report(result, path: str | os.PathLike, *, recordings=None,
                             targets=None, nominal: System | None = None,
                             max_std: dict | None = None, header: dict | None = None) -> Path:
    """Render the calibration report (PDF) of a result or of a failed calibration.

    Parameters
    ----------
    result : a :class:`~mems_stereo.calib.result.CalibrationResult` (4 pages), a
        :class:`~mems_stereo.calib.result.CalibrationFailure` or an exception
        (2 pages: why, and what the fit learnt), or a ready :class:`ReportData`.
    path : output ``.pdf`` (written atomically); ``.json`` writes
        :func:`write_calibration_report_json` instead.
    recordings : the calibration's recordings (Recordings or FORMAT v1 paths),
        for the residual and top-view pages (and a failure's TDC-time
        histograms); matched to the result's walls by source name.
    targets : the same already reduced (:class:`~mems_stereo.calib.problem.WallData`),
        instead of ``recordings``.
    nominal : the nominal system (a failure's "nominal" column).
    max_std : σ limits (SI) per parameter, as given to the fit.
    header : page 1's record (date, version, device, operator, input files with
        their SHA-256; :func:`~mems_stereo.viz.calib_report_header.report_header`).

    Returns the path.  Raises FormatError when ``path`` is neither ``.pdf`` nor ``.json``.
    """
    from matplotlib.backends.backend_pdf import PdfPages

    p = Path(path)
    if p.suffix.lower() == ".json":
        return write_calibration_report_json(result, p, recordings=recordings, targets=targets,
                                             nominal=nominal, max_std=max_std, header=header)
    if p.suffix.lower() != ".pdf":
        raise FormatError(f"expected a .pdf or .json file name, found {p.name!r}", str(p))
    d = report_data(result, nominal=nominal, max_std=max_std, header=header)
    walls = load_walls(recordings, targets)
    with atomic_output(p) as tmp, PdfPages(str(tmp)) as pdf:
        _summary_page(pdf, d)
        if d.ok:
            res = report_residuals(d, walls)
            if d.names:
                _estimates_page(pdf, d)
            _residual_page(pdf, d, res)
            _planes_page(pdf, d, res, d.system)
            from mems_stereo.viz.calib_report_hardware import hardware_page

            hardware_page(pdf, result)  # issue 30: hardware terms, goodness of fit
        else:
            _failure_page(pdf, d, _time_histograms(walls) if walls else [])
        info = pdf.infodict()
        info["Title"] = "mems-stereo calibration report"
        info["Subject"] = verdict(d)[0]
        if d.header:
            info["Author"] = d.header.get("operator") or ""
            info["Keywords"] = (f"device {d.header.get('device_id') or '-'}; "
                                f"mems-stereo {d.header.get('version')}")
    return p


def write_calibration_report_json(result, path: str | os.PathLike, *, recordings=None,
                                  targets=None, nominal: System | None = None,
                                  max_std: dict | None = None,
                                  header: dict | None = None) -> Path:
    """The same report for machines: :func:`~mems_stereo.viz.calib_report_json.report_dict`
    written atomically as JSON (arguments as :func:`write_calibration_report`)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        raise FormatError(f"expected a .json file name, found {p.name!r}", str(p))
    d = report_data(result, nominal=nominal, max_std=max_std, header=header)
    res = report_residuals(d, load_walls(recordings, targets))
    obj = report_dict(d, res, result if not isinstance(result, ReportData) else None)
    return atomic_write_text(p, json.dumps(obj, indent=1, allow_nan=False) + "\n")
