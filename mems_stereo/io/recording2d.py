"""HDF5 recordings of a two-axis scanner with a 2-D SPAD array (FORMAT v1 extension).

A two-axis recording is a FORMAT v1 recording (same attributes ``format``,
``version``, the same ``/system``, ``/shots/time`` and fast-axis monitor
``/scanner/zero_crossings``, ``/scanner/rising``) with the attribute
``scan_axes = 2`` and, instead of the dense ``/shots/bins``, the detections of
the pixels that were read, as an event list (``docs/formats.md``):

=================================== ============== =====================================
path                                type, shape    meaning
=================================== ============== =====================================
attrs ``scan_axes``                 int            2
``/scanner/axis2/zero_crossings``   float64 [Z2]   resonant axis 2: its zero crossings, s
``/scanner/axis2/rising``           uint8 [Z2]     1 where θ2_mech rose through zero
``/scanner/axis2/time``             float64 [P]    quasistatic axis 2: position samples, s
``/scanner/axis2/position``         float64 [P]    θ2_mech at those times, rad
``/readout`` attrs                  str, floats    ``mode`` "gated" or "full"; ``r_min``,
                                                   ``r_max`` m, ``half_width`` px (gated)
``/readout/count``                  uint16 [K]     pixels read in each shot
``/events/shot``                    uint32 [E]     shot index of each detection
``/events/pixel``                   uint32 [E]     flat pixel ``row · W + column``
``/events/code``                    uint16 [E]     TDC code 1..n_bins
``/truth/label``                    uint8 [E]      simulated only: 1 laser return, 2 background
=================================== ============== =====================================

Events are sorted by shot, then pixel; a read pixel without an event had no
detection.  A one-axis reader refuses the file (``/shots/bins`` is absent),
so nothing misreads it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.model.scanner import validate_zero_crossings
from mems_stereo.model.scanner2d import (
    Axis2Monitor,
    require_two_axis,
    validate_position_channel,
)
from mems_stereo.model.system import System, system_from_json, system_to_json
from mems_stereo.util.atomic import atomic_output

FORMAT_NAME = "mems-stereo/recording"
FORMAT_VERSION = 1
SCAN_AXES = 2


@dataclass
class Recording2D:
    """A two-axis recording in memory.

    system : System with ``scanner.axis2`` (nominal).
    shot_time : (K,) float64 s.
    zero_crossings, rising : (Z,) fast-axis monitor.
    monitor2 : :class:`~mems_stereo.model.scanner2d.Axis2Monitor`.
    readout : dict ``mode`` ("gated"/"full"), ``r_min``, ``r_max`` (m), ``half_width`` (px).
    read_count : (K,) int64 pixels read per shot.
    event_shot, event_pixel : (E,) int64; event_code : (E,) uint16.
    truth : optional ``label`` (E,) uint8, ``theta1``/``theta2`` (K,), ``point`` (K, 3),
        and scalar attributes.
    """

    system: System
    shot_time: np.ndarray
    zero_crossings: np.ndarray
    rising: np.ndarray
    monitor2: Axis2Monitor
    readout: dict
    read_count: np.ndarray
    event_shot: np.ndarray
    event_pixel: np.ndarray
    event_code: np.ndarray
    truth: dict = field(default_factory=dict)
    source: str = "<memory>"

    @property
    def n_shots(self) -> int:
        return int(self.shot_time.size)

    @property
    def n_events(self) -> int:
        return int(self.event_code.size)


def is_two_axis_recording(path: str | os.PathLike) -> bool:
    """True when the HDF5 file carries ``scan_axes = 2`` (False for v1 or unreadable files)."""
    try:
        with h5py.File(path, "r") as f:
            return int(np.asarray(f.attrs.get("scan_axes", 1))) == SCAN_AXES
    except (OSError, ValueError, TypeError):
        return False


def _need(f, path, source):
    if path not in f or not isinstance(f[path], h5py.Dataset):
        raise FormatError("required dataset is missing", source, path)
    return f[path][()]


def read_recording_2d(path: str | os.PathLike, *, truth: bool = True) -> Recording2D:
    """Read and validate a two-axis recording (errors: :class:`FormatError`)."""
    source = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise FormatError(f"cannot open as HDF5 ({e})", source) from None
    with f:
        fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT_NAME:
            raise FormatError(f"expected attribute format = {FORMAT_NAME!r}, found {fmt!r}",
                              source, "attrs/format")
        ver = f.attrs.get("version")
        if ver is None or int(np.asarray(ver)) != FORMAT_VERSION:
            raise FormatError(f"expected attribute version = {FORMAT_VERSION}, found {ver!r}",
                              source, "attrs/version")
        ax = int(np.asarray(f.attrs.get("scan_axes", 1)))
        if ax != SCAN_AXES:
            raise FormatError(f"expected attribute scan_axes = 2, found {ax}", source,
                              "attrs/scan_axes")
        raw = _need(f, "/system", source)
        raw = raw.decode("utf-8") if isinstance(raw, bytes) else raw
        system = system_from_json(raw, source=f"{source}:/system")
        a2 = require_two_axis(system, f"{source}:/system")
        t = np.asarray(_need(f, "/shots/time", source), dtype=np.float64)
        if t.ndim != 1 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise FormatError("expected (K,) finite, strictly increasing times", source,
                              "/shots/time")
        zc, rising = validate_zero_crossings(_need(f, "/scanner/zero_crossings", source),
                                             _need(f, "/scanner/rising", source), source)
        if a2.mode == "resonant":
            z2, r2 = validate_zero_crossings(
                _need(f, "/scanner/axis2/zero_crossings", source),
                _need(f, "/scanner/axis2/rising", source), source,
                field="/scanner/axis2/zero_crossings")
            mon = Axis2Monitor(zero_crossings=z2, rising=r2.astype(np.uint8))
        else:
            pt, pp = validate_position_channel(_need(f, "/scanner/axis2/time", source),
                                               _need(f, "/scanner/axis2/position", source),
                                               source)
            mon = Axis2Monitor(time=pt, position=pp)
        if "readout" not in f:
            raise FormatError("required group is missing", source, "/readout")
        ra = f["readout"].attrs
        mode = ra.get("mode")
        mode = mode.decode() if isinstance(mode, bytes) else mode
        if mode not in ("gated", "full"):
            raise FormatError(f"expected 'gated' or 'full', found {mode!r}", source,
                              "/readout attrs/mode")
        readout = {"mode": mode}
        if mode == "gated":
            for k in ("r_min", "r_max", "half_width"):
                if k not in ra:
                    raise FormatError("required attribute is missing", source,
                                      f"/readout attrs/{k}")
                readout[k] = float(ra[k])
        count = np.asarray(_need(f, "/readout/count", source)).astype(np.int64)
        if count.shape != t.shape:
            raise FormatError(f"expected shape {t.shape}, found {count.shape}", source,
                              "/readout/count")
        es = np.asarray(_need(f, "/events/shot", source)).astype(np.int64)
        ep = np.asarray(_need(f, "/events/pixel", source)).astype(np.int64)
        ec = np.asarray(_need(f, "/events/code", source))
        if not (es.shape == ep.shape == ec.shape) or es.ndim != 1:
            raise FormatError(f"expected equal (E,) shapes, found {es.shape}, {ep.shape}, "
                              f"{ec.shape}", source, "/events")
        if ec.dtype != np.uint16:
            raise FormatError(f"expected dtype uint16, found {ec.dtype}", source,
                              "/events/code")
        w, h = system.receiver.image_size
        n_bins = system.tdc.n_bins
        if es.size:
            if es.min() < 0 or es.max() >= t.size:
                raise FormatError(f"expected shot indices 0..{t.size - 1}, found "
                                  f"{es.min()}..{es.max()}", source, "/events/shot")
            if ep.min() < 0 or ep.max() >= w * h:
                raise FormatError(f"expected pixel indices 0..{w * h - 1}, found "
                                  f"{ep.min()}..{ep.max()}", source, "/events/pixel")
            if ec.min() < 1 or ec.max() > n_bins:
                raise FormatError(f"expected codes 1..{n_bins}, found {ec.min()}..{ec.max()}",
                                  source, "/events/code")
            key = es * (w * h) + ep
            if np.any(np.diff(key) <= 0):
                raise FormatError("expected events sorted by shot then pixel, one per slot",
                                  source, "/events")
        tr: dict = {}
        if truth and "truth" in f:
            for k, v in f["truth"].items():
                if isinstance(v, h5py.Dataset):
                    tr[k] = v[()]
            tr.update({k: v for k, v in f["truth"].attrs.items()})
    return Recording2D(system, t, zc, rising.astype(np.uint8), mon, readout, count, es, ep,
                       ec, tr, source)


def write_recording_2d(path: str | os.PathLike, rec: Recording2D,
                       compression: str | None = "gzip") -> Path:
    """Write a two-axis recording atomically (gzip + shuffle by default).

    Truth arrays of ``rec.truth`` go under ``/truth`` (scalars as its attributes).
    """
    system = rec.system
    a2 = require_two_axis(system)
    opts = {"compression": compression, "shuffle": True} if compression else {}

    def ds(f, name, data):
        data = np.asarray(data)
        f.create_dataset(name, data=data, **(opts if data.size > 16 else {}))

    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["version"] = FORMAT_VERSION
        f.attrs["scan_axes"] = SCAN_AXES
        f.create_dataset("system", data=system_to_json(system))
        ds(f, "shots/time", np.asarray(rec.shot_time, np.float64))
        ds(f, "scanner/zero_crossings", np.asarray(rec.zero_crossings, np.float64))
        ds(f, "scanner/rising", np.asarray(rec.rising, np.uint8))
        m = rec.monitor2
        if a2.mode == "resonant":
            ds(f, "scanner/axis2/zero_crossings", np.asarray(m.zero_crossings, np.float64))
            ds(f, "scanner/axis2/rising", np.asarray(m.rising, np.uint8))
        else:
            ds(f, "scanner/axis2/time", np.asarray(m.time, np.float64))
            ds(f, "scanner/axis2/position", np.asarray(m.position, np.float64))
        g = f.create_group("readout")
        for k, v in rec.readout.items():
            g.attrs[k] = v
        ds(f, "readout/count", np.asarray(rec.read_count).astype(np.uint16))
        ds(f, "events/shot", np.asarray(rec.event_shot).astype(np.uint32))
        ds(f, "events/pixel", np.asarray(rec.event_pixel).astype(np.uint32))
        ds(f, "events/code", np.asarray(rec.event_code, np.uint16))
        if rec.truth:
            tg = f.create_group("truth")
            for k, v in rec.truth.items():
                v = np.asarray(v)
                if v.ndim == 0:
                    tg.attrs[k] = v
                else:
                    ds(f, f"truth/{k}", v)
    return Path(path)
