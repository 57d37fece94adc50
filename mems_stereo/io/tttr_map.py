"""The mapping file of a time-tagged event stream (``mems-stereo/tttr-map``).

Which input channel is which pixel, what clocks the shots, which events carry
the mirror's zero-crossing monitor and how a photon's delay becomes a TDC code;
the format is documented in ``docs/formats.md`` and used by
:mod:`mems_stereo.io.tttr`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mems_stereo.model.presets import UnknownPresetError, looks_like_path
from mems_stereo.model.system import System, resolve_system, system_from_dict
from mems_stereo.util.jsonfile import FieldChecker, check_schema, read_json_file, shown
from mems_stereo.util.schemas import MAP_FIELDS

MAP_FORMAT = "mems-stereo/tttr-map"


@dataclass(frozen=True)
class TttrMap:
    """A parsed mapping file (see the module docstring and docs/formats.md).

    Attributes
    ----------
    pixels : (C, 3) int64 rows ``[channel, column, row]``.
    clock : "sync" or "channel"; clock_channel : int (when "channel").
    zc_source : "marker" or "channel"; zc_rising_edge, zc_falling_edge :
        marker number (1..4) or channel, or None; zc_positive : True when the
        monitor's rising edge means θ_mech increasing; zc_delay : s,
        subtracted from monitor event times.
    binning, delay_bins : TDC code = ticks // binning − delay_bins + 1.
    photons : "first" or "all"; n_shots : int or None (T2: default all
        syncs; T3: through the last event's sync); first_shot : the sync
        (T2: the sync event index, T3: the sync count) that is shot 0.
    time_origin : s, added to every time written (shots, zero crossings):
        the stream's time zero on the recording's clock.
    system : System (nominal) or None when the caller gives one.
    """

    pixels: np.ndarray
    clock: str = "sync"
    clock_channel: int | None = None
    zc_source: str = "marker"
    zc_rising_edge: int | None = 1
    zc_falling_edge: int | None = 2
    zc_positive: bool = True
    zc_delay: float = 0.0
    binning: int = 1
    delay_bins: int = 0
    photons: str = "first"
    n_shots: int | None = None
    first_shot: int = 0
    time_origin: float = 0.0
    system: System | None = field(default=None, compare=False)


def _int(ck: FieldChecker, v, fld: str, lo: int = 0) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ck.fail(fld, f"expected an integer >= {lo}, found {shown(v)}")
    return int(v)


def map_from_dict(d: dict, source: str = "<dict>", base_dir: str | os.PathLike = ".") -> TttrMap:
    """Validate a mapping object; errors name the field, expected vs found."""
    ck = FieldChecker(source)
    check_schema(d, MAP_FIELDS, ck)  # format, version, members and types
    fmt = ck.req(d, "format", "")
    if fmt != MAP_FORMAT:
        raise ck.fail("format", f"expected {MAP_FORMAT!r}, found {shown(fmt)}")
    ver = ck.req(d, "version", "")
    if ver != 1:
        raise ck.fail("version", f"expected 1, found {shown(ver)}")
    pixels = _pixels_from(ck, ck.req(d, "pixels", ""))
    sc = d.get("shot_clock", {"source": "sync"})
    src = ck.req(sc, "source", "shot_clock")
    if src not in ("sync", "channel"):
        raise ck.fail("shot_clock.source", f"expected 'sync' or 'channel', found {shown(src)}")
    clock_ch = _int(ck, ck.req(sc, "channel", "shot_clock"), "shot_clock.channel") \
        if src == "channel" else None
    zc = ck.req(d, "zero_crossings", "")
    zsrc = ck.req(zc, "source", "zero_crossings")
    if zsrc not in ("marker", "channel"):
        raise ck.fail("zero_crossings.source", f"expected 'marker' or 'channel', found "
                                               f"{shown(zsrc)}")
    edges = _edges_from(ck, zc, zsrc)
    if edges == [None, None]:
        raise ck.fail("zero_crossings", "expected rising_edge or falling_edge (or both)")
    pol = zc.get("polarity", "positive")
    if pol not in ("positive", "negative"):
        raise ck.fail("zero_crossings.polarity", f"expected 'positive' or 'negative', found "
                                                 f"{shown(pol)}")
    delay = ck.number(zc.get("delay", 0.0), "zero_crossings.delay")
    tdc = d.get("tdc", {})
    if not isinstance(tdc, dict):
        raise ck.fail("tdc", f"expected an object, found {shown(tdc)}")
    binning = _int(ck, tdc.get("binning", 1), "tdc.binning", 1)
    delay_bins = tdc.get("delay_bins", 0)
    if isinstance(delay_bins, bool) or not isinstance(delay_bins, int):
        raise ck.fail("tdc.delay_bins", f"expected an integer, found {shown(delay_bins)}")
    photons = d.get("photons", "first")
    if photons not in ("first", "all"):
        raise ck.fail("photons", f"expected 'first' or 'all', found {shown(photons)}")
    shots = d.get("shots", {})
    if not isinstance(shots, dict):
        raise ck.fail("shots", f"expected an object, found {shown(shots)}")
    n_shots = shots.get("count")
    if n_shots is not None:
        n_shots = _int(ck, n_shots, "shots.count", 1)
    first_shot = _int(ck, shots.get("first", 0), "shots.first")
    time_origin = ck.number(d.get("time_origin", 0.0), "time_origin")
    system = _system_from(ck, d["system"], source, base_dir) if "system" in d else None
    return TttrMap(pixels, src, clock_ch, zsrc, edges[0], edges[1], pol == "positive", delay,
                   binning, int(delay_bins), photons, n_shots, first_shot, time_origin,
                   system)


def _pixels_from(ck: FieldChecker, px) -> np.ndarray:
    """``pixels``: (C, 3) int64 rows [channel, column, row], each channel once."""
    if not isinstance(px, list) or not px:
        raise ck.fail("pixels", f"expected a list of [channel, column, row], found {shown(px)}")
    rows = []
    for i, p in enumerate(px):
        if isinstance(p, dict):
            p = [ck.req(p, "channel", f"pixels[{i}]"), ck.req(p, "column", f"pixels[{i}]"),
                 p.get("row", 0)]
        if not isinstance(p, list) or len(p) != 3:
            raise ck.fail(f"pixels[{i}]", f"expected [channel, column, row], found {shown(p)}")
        rows.append([_int(ck, v, f"pixels[{i}][{j}]") for j, v in enumerate(p)])
    pixels = np.asarray(rows, dtype=np.int64)
    if np.unique(pixels[:, 0]).size != len(rows):
        raise ck.fail("pixels", "expected each channel once, found a channel twice")
    return pixels


def _edges_from(ck: FieldChecker, zc: dict, zsrc: str) -> list[int | None]:
    """``[rising_edge, falling_edge]`` of ``zero_crossings``: markers 1..4 or channels."""
    edges = []
    for key in ("rising_edge", "falling_edge"):
        v = zc.get(key)
        edges.append(None if v is None else _int(ck, v, f"zero_crossings.{key}",
                                                  1 if zsrc == "marker" else 0))
        if zsrc == "marker" and v is not None and v > 4:
            raise ck.fail(f"zero_crossings.{key}", f"expected a marker 1..4, found {shown(v)}")
    return edges


def _system_from(ck: FieldChecker, spec, source: str, base_dir: str | os.PathLike) -> System:
    """``system``: an object, or a file name (relative to ``base_dir``) or preset."""
    if isinstance(spec, dict):
        return system_from_dict(spec, source=f"{source}:system")
    if isinstance(spec, str):
        p = Path(spec)
        cand = p if p.is_absolute() else Path(base_dir) / p
        as_path = cand.exists() or looks_like_path(spec)
        try:
            return resolve_system(str(cand) if as_path else spec)
        except UnknownPresetError as e:  # named as the map's field (the file, relative to it)
            raise ck.fail("system", f"{cand}: {e.reason}" if as_path else e.reason) from None
    raise ck.fail("system", f"expected a file name, preset or object, found {shown(spec)}")


def load_map(path: str | os.PathLike) -> TttrMap:
    """Read and validate a mapping JSON file (``system`` paths relative to it)."""
    return map_from_dict(read_json_file(path), str(path), Path(path).parent)


def map_to_dict(m: TttrMap, system: str | None = None) -> dict:
    """The JSON object of a mapping (``system``: the file name or preset to write)."""
    d = {"format": MAP_FORMAT, "version": 1,
         "pixels": [[int(a), int(b), int(c)] for a, b, c in m.pixels],
         "shot_clock": {"source": m.clock} | ({"channel": m.clock_channel}
                                              if m.clock == "channel" else {}),
         "zero_crossings": {"source": m.zc_source, "rising_edge": m.zc_rising_edge,
                            "falling_edge": m.zc_falling_edge,
                            "polarity": "positive" if m.zc_positive else "negative",
                            "delay": m.zc_delay},
         "tdc": {"binning": m.binning, "delay_bins": m.delay_bins},
         "photons": m.photons}
    d["shots"] = {"first": m.first_shot} | ({"count": m.n_shots} if m.n_shots else {})
    d["time_origin"] = m.time_origin
    if system is not None:
        d["system"] = system
    return d
