"""The calibration report for machines: the PDF's content as one JSON object.

:func:`report_dict` gives what :func:`~mems_stereo.viz.calib_report.write_calibration_report`
draws, as JSON-able values (``calibrate --report R.json``):

=============== ==============================================================
key             content
=============== ==============================================================
format          ``"mems-stereo/calibration-report"``; ``version`` 1
header          date (UTC), version, device id, operator, input files with
                SHA-256 (:mod:`mems_stereo.viz.calib_report_header`)
ok, verdict     a result exists; "CONVERGED", "CONVERGED, WEAK" or "FAILED"
verdict_lines   the observability verdict and the failed checks (text)
reason, kind    why a calibration failed ("" for a result)
units           the one display unit per quantity (:data:`REPORT_UNITS`)
parameters      per estimate: name, unit, nominal, estimate, std, pull (σ)
rms             headline RMS: ``pixel_px``, ``time_ns`` (first-photon shift removed)
walls           per wall: source, distance and σ (m), measured distance (m),
                tilt (mrad), signal photons per shot, spot σ (px), signal
                explained (%, at most 100), time residual mean and RMS (ns)
residuals       per wall recomputed from the recordings (when given): inlier
                count, pixel mean and RMS (px), time mean and RMS (ns)
checks          rows: name, quantity, unit, measured, fitted, limit, passed, text
record_next     advice, never repeating what was done
warnings        the fit's warnings
result          the calibration's own dict (``to_dict()``: covariance, …), or None
=============== ==============================================================
"""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib.association import wall_data
from mems_stereo.viz.calib_report_checks import REPORT_UNITS
from mems_stereo.viz.calib_report_data import (
    UNITS,
    ReportData,
    WallResiduals,
    checks_of,
    inliers,
    record_next,
    source_stem,
    verdict,
    wall_residuals,
)

from mems_stereo.errors import FormatError
from mems_stereo.io.recording import Recording, read_recording

FORMAT_NAME = "mems-stereo/calibration-report"


def _f(v, factor: float = 1.0):
    if v is None:
        return None
    x = float(v) * factor
    return x if math.isfinite(x) else None


def jsonable(v):
    """``v`` with NumPy values as Python ones, non-finite floats as None and anything
    else unknown as its text: strict JSON whatever a result carries."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [jsonable(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _f(v)
    if v is None or isinstance(v, str):
        return v
    return str(v)


def load_walls(recordings=None, targets=None) -> list | None:
    """The calibration's walls reduced for the report: ``targets`` as given, else
    each recording (Recording or path) through
    :func:`~mems_stereo.calib.association.wall_data` (one without a known phase
    is left out); None when neither is given."""
    if targets is not None:
        return list(targets)
    if recordings is None:
        return None
    walls = []
    for r in recordings:
        rec = r if isinstance(r, Recording) else read_recording(r, truth=False)
        try:
            walls.append(wall_data(rec))
        except FormatError:  # no known phase: nothing to draw for it
            continue
    return walls


def report_residuals(d: ReportData, walls) -> list:
    """Per fitted wall its :class:`WallResiduals` (None where its recording is missing),
    matched by source name; [] when no wall has a recording."""
    if not walls or not d.ok:
        return []
    by_name = {source_stem(w.source): w for w in walls}
    res = []
    for j, nm in enumerate(d.target_names):
        w = by_name.get(nm)
        res.append(None if w is None or j >= len(d.planes)
                   else wall_residuals(d.system, w, d.planes[j],
                                       target=d.walls[j] if j < len(d.walls) else None))
    return [] if all(r is None for r in res) else res


def residual_summary(r: WallResiduals) -> dict:
    """Inlier count and the mean and RMS of the pixel (px) and time (ns) residuals."""
    ok = inliers(r)
    n = int(ok.sum())

    def stats(v, f):
        if not n:
            return None, None
        x = v[ok] * f
        return float(np.mean(x)), float(np.sqrt(np.mean(x * x)))
    pm, pr = stats(r.res_pixel, 1.0)
    tm, tr = stats(r.res_time, 1e9)
    return {"inliers": n, "outliers": int(r.pixel.size - n), "pixel_mean_px": pm,
            "pixel_rms_px": pr, "time_mean_ns": tm, "time_rms_ns": tr,
            "first_photon_removed": bool(r.first_photon)}


def _wall_entry(d: ReportData, j: int, t: dict) -> dict:
    share = t.get("signal_share")
    e = {"source": str(t.get("source", f"wall {j}")),
         "distance_axis_m": _f(t.get("distance_axis")),
         "distance_axis_std_m": _f(t.get("distance_axis_std")),
         "distance_measured_m": _f(t.get("distance_measured")),
         "distance_measured_std_m": _f(t.get("distance_measured_std")),
         "distance_kind": t.get("distance_kind"),
         "tilt_mrad": _f(d.planes[j, 0], 1e3) if j < len(d.planes) else None,
         "photons_per_shot": _f(t.get("mu")), "spot_px": _f(t.get("spot_px")),
         "signal_explained_pct": None if share is None else _f(min(float(share), 1.0), 100.0),
         "time_residual_mean_ns": _f(t.get("time_residual_mean"), 1e9),
         "time_residual_rms_ns": _f(t.get("time_residual_rms"), 1e9),
         "consistency_p": _f(t.get("consistency_p"))}
    return e


def report_dict(d: ReportData, residuals=(), result=None) -> dict:
    """The report as JSON-able values (the module's table); ``residuals`` from
    :func:`report_residuals`, ``result`` the calibration object (its ``to_dict()``
    is kept under ``result``)."""
    head, lines = verdict(d)
    params = []
    for n in d.names:
        f, unit = UNITS.get(n, (1.0, ""))
        s, v, nom = d.std.get(n, math.nan), d.values.get(n), d.initial.get(n)
        pull = ((v - nom) / s if v is not None and nom is not None and s > 0
                and math.isfinite(s) else None)
        params.append({"name": n, "unit": unit, "nominal": _f(nom, f), "estimate": _f(v, f),
                       "std": _f(s, f), "pull": _f(pull)})
    res = [None if r is None else dict(residual_summary(r), source=d.target_names[j])
           for j, r in enumerate(residuals)]
    to_dict = getattr(result, "to_dict", None)
    return jsonable({"format": FORMAT_NAME, "version": 1, "header": d.header, "ok": d.ok,
            "verdict": head, "verdict_lines": lines, "reason": d.reason, "kind": d.kind,
            "units": {k: u for k, (_, u) in REPORT_UNITS.items()},
            "parameters": params, "fixed": list(d.fixed),
            "rms": {"pixel_px": _f(d.rms.get("pixel")), "time_ns": _f(d.rms.get("time"), 1e9),
                    "first_photon_removed": True} if d.rms else None,
            "n_detections": int(d.n_detections),
            "walls": [_wall_entry(d, j, t) for j, t in enumerate(d.walls)],
            "residuals": res, "checks": checks_of(d), "record_next": record_next(d),
            "warnings": list(d.warnings),
            "result": to_dict() if callable(to_dict) else None})
