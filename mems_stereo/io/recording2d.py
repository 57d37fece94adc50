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
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.recording_checks import (
    FORMAT_NAME,
    FORMAT_VERSION,
    check_shot_stride,
    read_crossings,
    read_shot_times,
    read_truth,
    validate_header,
)
from mems_stereo.model.scanner2d import (
    Axis2Monitor,
    require_two_axis,
    validate_position_channel,
)
from mems_stereo.model.system import System, system_to_json
from mems_stereo.util.atomic import atomic_output

SCAN_AXES = 2


@dataclass
class Recording2D:
    """A two-axis recording in memory.

    Attributes
    ----------
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
    """True when the HDF5 file carries ``scan_axes = 2`` (False for v1 or unreadable files:
    their reader then says what is wrong)."""
    try:
        with h5.open_h5(path) as f:
            return h5.attr_int(f, "scan_axes", str(path)) == SCAN_AXES
    except (FormatError, OSError):
        return False


def _whole(f, path: str, source: str, kinds: str | None = None, what: str = "") -> np.ndarray:
    """A dataset read whole through the safe reader (:mod:`mems_stereo.io.hdf5`);
    ``kinds``: the accepted dtype kinds (``"iu"``: integers)."""
    ds = h5.dataset(f, path, source, whole=True)
    if kinds is not None and ds.dtype.kind not in kinds:
        raise FormatError(f"expected {what or 'integers'}, found dtype {ds.dtype}", source, path)
    return h5.read(ds, source)


def _readout(f, source: str) -> dict:
    """``/readout`` attributes: ``mode`` and, gated, ``r_min``, ``r_max`` (m), ``half_width``."""
    try:
        g = f["readout"] if "readout" in f else None
        if not isinstance(g, h5py.Group):
            raise FormatError("required group is missing", source, "/readout")
        ra = dict(g.attrs.items())
    except h5.H5_ERRORS as e:
        raise FormatError(f"cannot read the attributes ({e})", source, "/readout") from None
    mode = ra.get("mode")
    mode = mode.decode("utf-8", "replace") if isinstance(mode, bytes) else mode
    if mode not in ("gated", "full"):
        raise FormatError(f"expected 'gated' or 'full', found {mode!r}"[:120], source,
                          "/readout attrs/mode")
    readout = {"mode": mode}
    if mode == "gated":
        for k in ("r_min", "r_max", "half_width"):
            if k not in ra:
                raise FormatError("required attribute is missing", source,
                                  f"/readout attrs/{k}")
            v = np.asarray(ra[k])
            if v.shape not in ((), (1,)) or v.dtype.kind not in "iuf":
                raise FormatError(f"expected a number, found {ra[k]!r}"[:120], source,
                                  f"/readout attrs/{k}")
            readout[k] = float(v.reshape(()))
        if not (0 < readout["r_min"] < readout["r_max"] < np.inf
                and 0 <= readout["half_width"] < np.inf):
            raise FormatError(f"expected 0 < r_min < r_max < inf (m) and a finite half_width "
                              f">= 0 (px), found r_min={readout['r_min']}, r_max="
                              f"{readout['r_max']}, half_width={readout['half_width']}",
                              source, "/readout attrs")
    return readout


def read_recording_2d(path: str | os.PathLike, *, truth: bool = True) -> Recording2D:
    """Read and validate a two-axis recording (errors: :class:`FormatError`).

    The header, the shot times, the fast axis' crossings and the truth are
    read and checked by the one-axis reader's functions
    (:mod:`mems_stereo.io.recording`), through the safe HDF5 layer
    (:mod:`mems_stereo.io.hdf5`: links, layout, memory budget, corrupt chunks).
    """
    source = str(path)
    with h5.open_h5(path) as f:
        system = validate_header(f, source, scan_axes=SCAN_AXES)
        a2 = require_two_axis(system, f"{source}:/system")
        t = read_shot_times(f, source)
        check_shot_stride(t, system.laser.f_rep, source)
        zc, rising = read_crossings(f, source, system.scanner.f_mech)
        if a2.mode == "resonant":
            z2, r2 = read_crossings(f, source, a2.f_mech, "/scanner/axis2")
            mon = Axis2Monitor(zero_crossings=z2, rising=r2)
        else:
            pt, pp = validate_position_channel(
                _whole(f, "/scanner/axis2/time", source, "f", "float seconds"),
                _whole(f, "/scanner/axis2/position", source, "f", "float radians"), source)
            mon = Axis2Monitor(time=pt, position=pp)
        readout = _readout(f, source)
        count = _whole(f, "/readout/count", source, "iu").astype(np.int64)
        if count.shape != t.shape:
            raise FormatError(f"expected shape {t.shape}, found {count.shape}", source,
                              "/readout/count")
        es = _whole(f, "/events/shot", source, "iu").astype(np.int64)
        ep = _whole(f, "/events/pixel", source, "iu").astype(np.int64)
        ec = _whole(f, "/events/code", source)
        if not (es.shape == ep.shape == ec.shape) or es.ndim != 1:
            raise FormatError(f"expected equal (E,) shapes, found {es.shape}, {ep.shape}, "
                              f"{ec.shape}", source, "/events")
        if ec.dtype != np.uint16:
            raise FormatError(f"expected dtype uint16, found {ec.dtype}", source,
                              "/events/code")
        _check_events(es, ep, ec, t.size, system, source)
        tr = read_truth(f, source, attrs=True) if truth else {}
    return Recording2D(system, t, zc, rising, mon, readout, count, es, ep, ec, tr, source)


def _check_events(es, ep, ec, n_shots: int, system: System, source: str) -> None:
    w, h = system.receiver.image_size
    n_bins = system.tdc.n_bins
    if not es.size:
        return
    if es.min() < 0 or es.max() >= n_shots:
        raise FormatError(f"expected shot indices 0..{n_shots - 1}, found "
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
