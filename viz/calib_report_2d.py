"""The calibration report of a two-axis calibration (``calibrate --report`` on two-axis walls).

:func:`two_axis_report_dict` gives the JSON form (estimates with σ and their
nominal values, covariance and correlation, RMS residuals, χ²/dof, the fitted
walls); :func:`write_two_axis_report` renders the same as a PDF (matplotlib's
``PdfPages``, Agg, no display): page 1 the estimates and walls, page 2 the
correlation matrix.  A failed calibration gives the reason instead
(:func:`two_axis_failure_dict`, and one page in the PDF).  Both carry the
header a filed report needs (``header``: date, version, device id, operator,
input files with SHA-256; :mod:`mems_stereo.viz.calib_report_header`), on
page 1 of the PDF as in the line-sensor report.
"""

from __future__ import annotations

import math
import os
import textwrap
from pathlib import Path

import numpy as np
from mems_stereo.calib.twoaxis import TwoAxisCalibration, get_param_2d
from mems_stereo.viz.calib_report_header import header_lines

from mems_stereo.errors import FormatError
from mems_stereo.model.system import System
from mems_stereo.util.atomic import atomic_output


def _f(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def two_axis_report_dict(res: TwoAxisCalibration, *, recordings=(),
                         nominal: System | None = None, header: dict | None = None) -> dict:
    """Everything the two-axis fit learnt, as JSON-able values (SI units, angles rad),
    with the report's ``header``."""
    std = np.sqrt(np.clip(np.diag(res.cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = res.cov / np.outer(std, std)
    params = {n: {"value": _f(v), "std": _f(s),
                  "nominal": None if nominal is None else _f(get_param_2d(nominal, n))}
              for n, v, s in zip(res.names, res.values, res.std)}
    walls = [{"source": str(Path(r).name) if i < len(recordings) else None,
              "alpha_rad": _f(w[0]), "beta_rad": _f(w[1]), "distance_m": _f(w[2])}
             for i, (r, w) in enumerate(zip(list(recordings) + [None] * len(res.walls),
                                            res.walls))]
    return {"ok": True, "kind": "two-axis walls", "header": header, "parameters": params,
            "covariance": {"names": list(res.names),
                           "matrix": [[float(v) for v in row] for row in res.cov]},
            "correlation": [[_f(v) for v in row] for row in corr],
            "rms_pixel": _f(res.rms_px), "rms_path_m": _f(res.rms_L),
            "chi2_dof": _f(res.chi2_dof), "n_shots": int(res.n_obs), "walls": walls}


def two_axis_failure_dict(reason: str, *, recordings=(), header: dict | None = None) -> dict:
    """The report of a two-axis calibration that failed: why (and the ``header``)."""
    return {"ok": False, "kind": "two-axis walls", "header": header, "reason": reason,
            "recordings": [str(Path(r).name) for r in recordings]}


def _text_page(pdf, title: str, blocks: list[tuple[str, list[str]]]) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.27, 11.69))
    fig.text(0.06, 0.96, title, fontsize=15, weight="bold", va="top")
    y = 0.92
    for head, lines in blocks:
        fig.text(0.06, y, head, fontsize=11, weight="bold", va="top")
        y -= 0.024
        for line in lines:
            for part in textwrap.wrap(line, 95, subsequent_indent="    ") or [""]:
                if y < 0.04:
                    break
                fig.text(0.08, y, part, fontsize=8.5, family="monospace", va="top")
                y -= 0.017
        y -= 0.012
    pdf.savefig(fig)


def _estimate_lines(d: dict) -> list[str]:
    lines = [f"{'parameter':20s} {'estimate':>14s} {'σ':>11s} {'nominal':>14s}"]
    for n, p in d["parameters"].items():
        nom = "" if p["nominal"] is None else f"{p['nominal']:14.6g}"
        sd = "nan" if p["std"] is None else f"{p['std']:.3g}"
        val = "nan" if p["value"] is None else f"{p['value']:14.6g}"
        lines.append(f"{n:20s} {val:>14s} {sd:>11s} {nom:>14s}")
    return lines


def _correlation_page(pdf, d: dict) -> None:
    from matplotlib.figure import Figure

    names = d["covariance"]["names"]
    corr = np.array([[np.nan if v is None else v for v in row] for row in d["correlation"]],
                    dtype=float)
    fig = Figure(figsize=(8.27, 8.27))
    ax = fig.add_axes((0.25, 0.2, 0.6, 0.6))
    im = ax.imshow(corr, vmin=-1, vmax=1, cmap="coolwarm")
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.set_title("correlation of the estimates")
    fig.colorbar(im, ax=ax, fraction=0.046)
    pdf.savefig(fig)


def write_two_axis_report(report: dict, path: str | os.PathLike) -> Path:
    """Render a :func:`two_axis_report_dict` (or :func:`two_axis_failure_dict`) as a PDF."""
    from matplotlib.backends.backend_pdf import PdfPages

    p = Path(path)
    if p.suffix.lower() != ".pdf":
        raise FormatError(f"expected a .pdf file name, found {p.name!r}", str(p))
    record = [("record", header_lines(report["header"]))] if report.get("header") else []
    with atomic_output(p) as tmp, PdfPages(str(tmp)) as pdf:
        if not report["ok"]:
            _text_page(pdf, "Two-axis calibration FAILED",
                       [*record, ("why", [report["reason"]]),
                        ("recordings", report["recordings"] or ["-"])])
            return p
        walls = [f"{w['source'] or '-':28s} α {w['alpha_rad'] * 1e3:8.2f} mrad  "
                 f"β {w['beta_rad'] * 1e3:8.2f} mrad  distance {w['distance_m']:.4f} m"
                 for w in report["walls"]]
        _text_page(pdf, "Two-axis calibration", [
            *record,
            ("estimates (SI units: m, rad, s; intrinsics px)", _estimate_lines(report)),
            ("residuals", [f"RMS pixel {report['rms_pixel']:.3f} px, path "
                           f"{report['rms_path_m'] * 1e3:.1f} mm; χ²/dof "
                           f"{report['chi2_dof']:.2f}; {report['n_shots']} shots"]),
            ("walls (fitted poses)", walls)])
        if report["covariance"]["names"]:
            _correlation_page(pdf, report)
    return p
