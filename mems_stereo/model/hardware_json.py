"""The hardware model's members of the system JSON: read, validate, write.

The optional members of ``docs/hardware.md`` (``scanner.harmonics``,
``scanner.monitor``, ``laser.pulse_shape``, ``tdc.pixel_offsets``,
``tdc.code_widths`` and their σ): a version-1 file without them reads into the
ideal hardware, and :func:`hardware_to_dict` writes nothing for it, so such a
file round-trips byte for byte.  The member types are checked by the declared
schema (:data:`mems_stereo.util.schemas.SYSTEM_FIELDS`); the values here.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from mems_stereo.model.hardware import (
    TDC,
    Harmonic,
    Laser,
    MonitorEdges,
    PulseModel,
    Receiver,
    Scanner,
)
from mems_stereo.util.jsonfile import FieldChecker

#: a harmonic's amplitude (relative to θ_mech,max) above which the trajectory is refused
MAX_HARMONIC_AMPLITUDE = 0.2
#: largest edge delay, s (a MEMS period is ~0.1–1 ms)
MAX_EDGE_DELAY = 1e-4
#: code widths accepted, in LSB
CODE_WIDTH_RANGE = (0.0, 10.0)


def _opt(ctx: FieldChecker, d: dict, key: str, fld: str, nonneg: bool = False):
    return None if d.get(key) is None else ctx.number(d[key], f"{fld}.{key}", nonneg=nonneg)


def _harmonics(items: list, ctx: FieldChecker) -> tuple:
    out, seen = [], set()
    for i, h in enumerate(items):
        fld = f"scanner.harmonics[{i}]"
        k = h["order"]
        if k < 2 or k > 64 or k in seen:
            raise ctx.fail(f"{fld}.order", f"expected a distinct integer in 2..64, found {k!r}")
        seen.add(k)
        a = ctx.number(h["amplitude"], f"{fld}.amplitude")
        if abs(a) > MAX_HARMONIC_AMPLITUDE:
            raise ctx.fail(f"{fld}.amplitude", f"expected |A| <= {MAX_HARMONIC_AMPLITUDE} "
                                               f"(relative to theta_mech_max), found {a!r}")
        out.append(Harmonic(int(k), a, ctx.number(h.get("phase", 0.0), f"{fld}.phase"),
                            _opt(ctx, h, "amplitude_std", fld, True),
                            _opt(ctx, h, "phase_std", fld, True)))
    return tuple(sorted(out, key=lambda h: h.order))


def _monitor(m: dict, ctx: FieldChecker) -> MonitorEdges:
    fld = "scanner.monitor"
    vals = {}
    for key in ("rising_delay", "falling_delay"):
        v = ctx.number(m[key], f"{fld}.{key}")
        if abs(v) > MAX_EDGE_DELAY:
            raise ctx.fail(f"{fld}.{key}", f"expected |delay| <= {MAX_EDGE_DELAY:g} s, found {v!r}")
        vals[key] = v
    return MonitorEdges(vals["rising_delay"], vals["falling_delay"],
                        _opt(ctx, m, "rising_delay_std", fld, True),
                        _opt(ctx, m, "falling_delay_std", fld, True))


def _pulse(p: dict, ctx: FieldChecker) -> PulseModel:
    fld = "laser.pulse_shape"
    model = p["model"]
    if model == "ex-gaussian":
        w = ctx.number(p.get("tail_fraction", 0.0), f"{fld}.tail_fraction", nonneg=True)
        if w >= 1.0:
            raise ctx.fail(f"{fld}.tail_fraction", f"expected a share in [0, 1), found {w!r}")
        tau = ctx.number(p.get("tail_decay", 0.0), f"{fld}.tail_decay", nonneg=True)
        if tau > 1e-6 or (w > 0 and tau <= 0):
            raise ctx.fail(f"{fld}.tail_decay", f"expected a decay time in (0, 1e-6] s, "
                                                f"found {tau!r}")
        return PulseModel("ex-gaussian", w, tau, _opt(ctx, p, "tail_fraction_std", fld, True),
                          _opt(ctx, p, "tail_decay_std", fld, True))
    if model == "table":
        t = ctx.array(ctx.req(p, "times", fld), f"{fld}.times", (None,))
        pw = ctx.array(ctx.req(p, "power", fld), f"{fld}.power", t.shape)
        if t.size < 2 or np.any(np.diff(t) <= 0) or np.any(pw < 0) or not np.any(pw > 0):
            raise ctx.fail(fld, "expected >= 2 increasing times and non-negative power "
                                "with a positive peak")
        return PulseModel("table", times=t, power=pw)
    raise ctx.fail(f"{fld}.model", f'expected "ex-gaussian" or "table", found {model!r}')


def _tdc(t: dict, tdc: TDC, n_pixels: int, ctx: FieldChecker) -> TDC:
    kw: dict[str, Any] = {}
    for key, n in (("pixel_offsets", n_pixels), ("pixel_offsets_std", n_pixels),
                   ("code_widths", tdc.n_bins), ("code_widths_std", tdc.n_bins)):
        if t.get(key) is not None:
            kw[key] = ctx.array(t[key], f"tdc.{key}", (n,))
    off = kw.get("pixel_offsets")
    if off is not None and np.any(np.abs(off) > 1e-6):
        raise ctx.fail("tdc.pixel_offsets", "expected offsets within ±1 µs")
    w = kw.get("code_widths")
    lo, hi = CODE_WIDTH_RANGE
    if w is not None and (np.any(w < lo) or np.any(w > hi) or not np.any(w > 0)):
        raise ctx.fail("tdc.code_widths", f"expected widths in [{lo:g}, {hi:g}] LSB, "
                                          "not all zero")
    for key in ("pixel_offsets_std", "code_widths_std"):
        if key in kw and np.any(kw[key] < 0):
            raise ctx.fail(f"tdc.{key}", "expected non-negative σ")
    return replace(tdc, **kw)


def hardware_from_dict(d: dict, receiver: Receiver, scanner: Scanner, laser: Laser, tdc: TDC,
                       ctx: FieldChecker):
    """(scanner, laser, tdc) with the hardware model's members of the system object ``d``
    (schema-checked already); unchanged where the file has none."""
    s, la, t = d["scanner"], d["laser"], d["tdc"]
    if s.get("harmonics"):
        scanner = replace(scanner, harmonics=_harmonics(s["harmonics"], ctx))
    if s.get("monitor") is not None:
        scanner = replace(scanner, monitor=_monitor(s["monitor"], ctx))
    if la.get("pulse_shape") is not None:
        laser = replace(laser, pulse_shape=_pulse(la["pulse_shape"], ctx))
    tdc = _tdc(t, tdc, receiver.width * receiver.height, ctx)
    return scanner, laser, tdc


def _std_items(obj, names) -> dict:
    return {n: float(getattr(obj, n)) for n in names if getattr(obj, n) is not None}


def hardware_to_dict(scanner: Scanner, laser: Laser, tdc: TDC, d: dict) -> None:
    """Add the hardware model's members to the system JSON object ``d`` (in place);
    nothing for ideal hardware."""
    if scanner.harmonics:
        d["scanner"]["harmonics"] = [
            {"order": int(h.order), "amplitude": float(h.amplitude), "phase": float(h.phase),
             **_std_items(h, ("amplitude_std", "phase_std"))} for h in scanner.harmonics]
    m = scanner.monitor
    if m is not None:
        d["scanner"]["monitor"] = {"rising_delay": float(m.rising_delay),
                                   "falling_delay": float(m.falling_delay),
                                   **_std_items(m, ("rising_delay_std", "falling_delay_std"))}
    p = laser.pulse_shape
    if p is not None and p.model == "table":
        d["laser"]["pulse_shape"] = {"model": "table",
                                     "times": np.asarray(p.times, float).tolist(),
                                     "power": np.asarray(p.power, float).tolist()}
    elif p is not None:
        d["laser"]["pulse_shape"] = {"model": p.model, "tail_fraction": float(p.tail_fraction),
                                     "tail_decay": float(p.tail_decay),
                                     **_std_items(p, ("tail_fraction_std", "tail_decay_std"))}
    for key in ("pixel_offsets", "pixel_offsets_std", "code_widths", "code_widths_std"):
        v = getattr(tdc, key)
        if v is not None:
            d["tdc"][key] = np.asarray(v, float).ravel().tolist()
