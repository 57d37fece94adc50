"""The plausibility checks as the report shows them: measured beside fitted, with units.

:func:`check_rows` turns the calibration's ``checks`` table (name → (value,
limit, passed), SI) and its per-wall values into rows that say what was
measured (a measured target distance), what the fit gives, the limit and the
outcome, each in the one unit the report uses for that quantity
(:data:`REPORT_UNITS`): ``wall 0 distance: measured 1.5000 m, fitted 1.4937 m,
limit ≥ 0.2 m: ok``.
"""

from __future__ import annotations

import math
import re

import numpy as np

#: the one display unit per quantity, everywhere in the report (PDF and JSON rows):
#: quantity → (factor from SI, unit)
REPORT_UNITS = {
    "wall distance": (1.0, "m"),
    "baseline": (1e3, "mm"),
    "angle": (1e3, "mrad"),
    "time": (1e9, "ns"),
    "pixel": (1.0, "px"),
    "share": (100.0, "%"),
    "pull": (1.0, "σ"),
}

_WALL = re.compile(r"^wall (\d+) (.+)$")
#: per-wall check kind → (quantity, display unit key or None, comparison)
_KINDS = {
    "distance": ("distance along the optical axis", "wall distance", "≥"),
    "tilt": ("tilt of the wall to the optical axis", "angle", "≤"),
    "signal explained": ("share of the returns above the background the fit explains "
                         "(at most 100 %)", "share", "≥"),
    "track points followed": ("share of the returns found on the sensor the fitted beam "
                              "follows", "share", "≥"),
    "spot σ above its bound": ("fitted spot σ", "pixel", ">"),
    "flat-wall consistency p": ("p-value of the flat-wall consistency test", None, "≥"),
    "measured distance pull": ("measured distance against a fit without it", "pull",
                               "|·| ≤"),
}


def _num(v, unit: str | None) -> float | None:
    if v is None or not isinstance(v, (int, float, np.floating, np.integer)):
        return None
    f = float(v) * (REPORT_UNITS[unit][0] if unit else 1.0)
    return f if math.isfinite(f) else None


def _fmt(v: float | None, unit: str | None) -> str:
    if v is None:
        return "—"
    u = REPORT_UNITS[unit][1] if unit else ""
    if unit == "wall distance":
        s = f"{v:.4f}"
    elif unit == "share":
        s = f"{v:.0f}"
    elif unit is None:
        s = f"{v:.2g}"
    else:
        s = f"{v:.4g}"
    return f"{s} {u}".rstrip() if u != "σ" else f"{s}σ"


def _row(name, quantity, unit, measured, fitted, limit, op, passed, extra="") -> dict:
    """One row (values in ``unit``) and its text."""
    lim = (f"{_fmt(limit[0], unit)} … {_fmt(limit[1], unit)}" if isinstance(limit, tuple)
           else f"{op} {_fmt(limit, unit)}")
    parts = []
    if measured is not None or unit == "wall distance":
        parts.append(f"measured {_fmt(measured, unit) if measured is not None else 'not given'}")
    parts.append(f"fitted {_fmt(fitted, unit)}")
    text = (f"{name}: {', '.join(parts)}{extra}, limit {lim}: "
            f"{'ok' if passed else 'FAILED'}")
    return {"name": name, "quantity": quantity,
            "unit": REPORT_UNITS[unit][1] if unit else "", "measured": measured,
            "fitted": fitted, "limit": list(limit) if isinstance(limit, tuple) else limit,
            "passed": bool(passed), "text": text}


def _wall_row(name: str, j: int, kind: str, val, lim, ok, walls: list) -> dict:
    quantity, unit, op = _KINDS[kind]
    t = walls[j] if j < len(walls) else {}
    fitted, limit, measured, extra = _num(val, unit), _num(lim, unit), None, ""
    if kind == "signal explained" and fitted is not None:
        fitted = min(fitted, 100.0)  # the excess over the background is a Poisson count
    if kind == "distance" and t.get("distance_measured") is not None:
        if t.get("distance_kind", "axis") == "axis":
            measured = _num(t["distance_measured"], unit)
        else:
            extra = (f" (measured {t['distance_measured']:.4f} m along the wall's "
                     f"{t['distance_kind']}, fitted {t.get('distance_fitted', math.nan):.4f} m)")
    if kind == "measured distance pull":
        measured, fitted = _num(t.get("distance_measured"), "wall distance"), _num(
            t.get("distance_fitted"), "wall distance")
        row = _row(name, quantity, "wall distance", measured, fitted, None, op, ok)
        pull = _num(val, None)
        row.update(unit="m", limit=_num(lim, None), pull=pull,
                   text=(f"{name.replace(' pull', '')}: measured {_fmt(measured, 'wall distance')}"
                         f", fitted {_fmt(fitted, 'wall distance')}, pull "
                         f"{pull if pull is not None else math.nan:+.1f}σ, limit |pull| ≤ "
                         f"{_num(lim, None) or math.nan:.0f}σ: {'ok' if ok else 'FAILED'}"))
        return row
    return _row(name, quantity, unit, measured, fitted, limit, op, ok, extra)


def _baseline_row(name: str, val, lim, ok, nominal, system) -> dict:
    extra = ""
    if nominal is not None and system is not None:
        bn = float(np.linalg.norm(nominal.baseline)) * 1e3
        bf = float(np.linalg.norm(system.baseline)) * 1e3
        extra = f" (nominal {bn:.2f} mm, fitted {bf:.2f} mm)"
    ratio = _num(val, None)
    lim_t = tuple(float(x) for x in lim) if isinstance(lim, (tuple, list)) else lim
    row = {"name": name, "quantity": "baseline length over its nominal length", "unit": "",
           "measured": None, "fitted": ratio, "limit": list(lim_t) if isinstance(lim_t, tuple)
           else lim_t, "passed": bool(ok)}
    lim_s = f"{lim_t[0]:g} … {lim_t[1]:g}" if isinstance(lim_t, tuple) else f"{lim_t}"
    row["text"] = (f"{name}: fitted {ratio if ratio is not None else math.nan:.3f}{extra}, "
                   f"limit {lim_s}: {'ok' if ok else 'FAILED'}")
    return row


def check_rows(checks: dict, walls: list, nominal=None, system=None) -> list[dict]:
    """The rows of the checks table, in its order.

    checks : name → (value, limit, passed) in SI (as
    :attr:`~mems_stereo.calib.result.CalibrationResult.checks`); walls : the
    per-wall dicts (``distance_measured``, ``distance_kind``,
    ``distance_fitted`` when distances were measured); nominal, system : the
    nominal and fitted systems (the baseline row's lengths; None: ratio only).

    Each row: ``name``, ``quantity``, ``unit`` (of ``measured``, ``fitted``
    and ``limit``), ``measured`` (None: nothing measured), ``fitted``,
    ``limit`` (a number or [low, high]), ``passed``, ``text``.  A check of an
    unknown shape gives a row with its value as ``fitted`` and no unit.
    """
    rows = []
    for name, v in checks.items():
        if not (isinstance(v, (tuple, list)) and len(v) == 3):
            rows.append({"name": name, "quantity": "", "unit": "", "measured": None,
                         "fitted": None, "limit": None, "passed": None,
                         "text": f"{name}: {v}"})
            continue
        val, lim, ok = v
        m = _WALL.match(name)
        if m and m.group(2) in _KINDS:
            rows.append(_wall_row(name, int(m.group(1)), m.group(2), val, lim, ok, walls))
        elif name == "baseline length / nominal":
            rows.append(_baseline_row(name, val, lim, ok, nominal, system))
        else:
            lim_t = tuple(lim) if isinstance(lim, (tuple, list)) else _num(lim, None)
            rows.append(_row(name, "", None, None, _num(val, None), lim_t, "", ok))
    return rows
