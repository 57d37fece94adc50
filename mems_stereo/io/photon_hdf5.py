"""Photon-HDF5 files (photon-hdf5.org, v0.4/0.5) as streamed event blocks, read with h5py.

Photon-HDF5 is plain HDF5 with a documented layout, so the reader needs
only h5py and streams ``/photon_data`` in blocks (memory bounded by the
block, whatever the file size).  ``phconvert`` (optional extra
``mems-stereo[photon-hdf5]``; installs on NumPy 2) converts Becker & Hickl
``.spc``/``.set``, PicoQuant ``.pt3``/``.ptu``/``.ht3`` and others *to*
Photon-HDF5; its own loader reads whole files into memory through
PyTables, which is why it is not used to read here.

What is read (single-spot files, ``/photon_data``):

- ``timestamps`` (n,) int, ``timestamps_specs/timestamps_unit`` (s);
- ``detectors`` (n,) int: the channel of each event (pixels, and the
  channels the mapping names for the shot clock or the mirror monitor);
- ``nanotimes`` (n,) int and ``nanotimes_specs/tcspc_unit`` (s), optional.

With nanotimes the stream is read like a T3 file (``timestamps`` count laser
syncs, so ``timestamps_unit`` must be the laser period, 1 /
``measurement_specs/laser_repetition_rate``; the shot clock is the sync);
without, like a T2 file (``timestamps`` are absolute times, the shot clock is
a detector channel: ``"shot_clock": {"source": "channel", "channel": ID}``).
Photon-HDF5 has no marker records: the mirror monitor must be a detector
channel (``"zero_crossings": {"source": "channel", ...}``).
"""

from __future__ import annotations

import os

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.ptu import EventBlock
from mems_stereo.io.tttr import StreamInfo
from mems_stereo.util.atomic import atomic_output

PHOTON = 0  # every Photon-HDF5 event is a detector event (mems_stereo.io.tttr codes)


def _scalar(f, path: str, source: str, required: bool = True):
    if path not in f:
        if required:
            raise FormatError("required Photon-HDF5 field is missing", source, path)
        return None
    v = h5.read(h5.dataset(f, path, source, whole=True), source)
    return v.item() if hasattr(v, "item") and np.size(v) == 1 else v


def _positive(v, source: str, path: str) -> float:
    """A positive finite number read from the file (anything else: FormatError)."""
    a = np.asarray(v)
    if a.size != 1 or a.dtype.kind not in "iuf" or not (0 < float(a.ravel()[0]) < np.inf):
        raise FormatError(f"expected a positive finite number, found {v!r}"[:120], source, path)
    return float(a.ravel()[0])


def _check_identity(f, source: str) -> None:
    """A single-spot file whose ``format_name``, when given, is Photon-HDF5."""
    if "photon_data" not in f:
        multi = [k for k in f if k.startswith("photon_data")]
        raise FormatError("expected a single-spot file with /photon_data"
                          + (f", found {multi}" if multi else ""), source, "/photon_data")
    name = f.attrs.get("format_name", _scalar(f, "identity/format_name", source, False))
    if isinstance(name, bytes):
        name = name.decode("utf-8", "replace")
    if name not in (None, "Photon-HDF5"):
        raise FormatError(f"expected format_name 'Photon-HDF5', found {name!r}"[:160], source,
                          "/identity/format_name")


def _t3_info(f, source: str, n: int, unit: float) -> StreamInfo:
    """The stream of a file with nanotimes: timestamps count laser periods."""
    nt = h5.dataset(f, "/photon_data/nanotimes", source)
    if nt.shape != (n,) or nt.dtype.kind not in "iu":
        raise FormatError(f"expected integer (n,) = ({n},) nanotimes", source,
                          "/photon_data/nanotimes")
    tcspc = _positive(_scalar(f, "photon_data/nanotimes_specs/tcspc_unit", source),
                      source, "/photon_data/nanotimes_specs/tcspc_unit")
    rate = _scalar(f, "photon_data/measurement_specs/laser_repetition_rate", source, False)
    rpath = "/photon_data/measurement_specs/laser_repetition_rate"
    if rate is None:
        rate = _scalar(f, "setup/laser_repetition_rates", source, False)
        rpath = "/setup/laser_repetition_rates"
        rate = None if rate is None else np.ravel(rate)[:1]
    rate = None if rate is None else _positive(rate, source, rpath)
    if rate is None or abs(unit * float(rate) - 1.0) > 1e-6:
        raise FormatError(f"with nanotimes, expected timestamps in laser periods "
                          f"(timestamps_unit = 1 / laser_repetition_rate), found "
                          f"unit {unit} s and rate {rate} Hz", source,
                          "/photon_data/timestamps_specs/timestamps_unit")
    return StreamInfo("T3", unit, tcspc, float(rate))


def photon_hdf5_stream(path: str | os.PathLike, block: int = 1 << 22):
    """``(StreamInfo, open_blocks)`` of a Photon-HDF5 file for :mod:`mems_stereo.io.tttr`.

    Opened and read through the safe HDF5 layer (:mod:`mems_stereo.io.hdf5`).
    """
    source = str(path)
    with h5.open_h5(path) as f:
        _check_identity(f, source)
        ts = h5.dataset(f, "/photon_data/timestamps", source)
        if ts.ndim != 1 or ts.dtype.kind not in "iu":
            raise FormatError("expected integer (n,) timestamps", source,
                              "/photon_data/timestamps")
        unit = _positive(_scalar(f, "photon_data/timestamps_specs/timestamps_unit", source),
                         source, "/photon_data/timestamps_specs/timestamps_unit")
        n = ts.shape[0]
        det = h5.dataset(f, "/photon_data/detectors", source)
        if det.shape != (n,) or det.dtype.kind not in "iu":
            raise FormatError(f"expected integer (n,) = ({n},) detectors", source,
                              "/photon_data/detectors")
        has_nt = "photon_data/nanotimes" in f
        info = _t3_info(f, source, n, unit) if has_nt else StreamInfo("T2", unit, unit, 0.0)

    def open_blocks():
        with h5.open_h5(path) as g:
            t = h5.dataset(g, "/photon_data/timestamps", source)
            d = h5.dataset(g, "/photon_data/detectors", source)
            nt = h5.dataset(g, "/photon_data/nanotimes", source) if has_nt else None
            last = None
            for a in range(0, n, block):
                sel = np.s_[a:a + block]
                mac = h5.read(t, source, sel).astype(np.int64)
                if mac.size and (np.any(np.diff(mac) < 0) or (last is not None
                                                               and mac[0] < last)):
                    raise FormatError("expected non-decreasing timestamps", source,
                                      "/photon_data/timestamps")
                if mac.size:
                    last = int(mac[-1])
                mic = (h5.read(nt, source, sel).astype(np.int64) if nt is not None
                       else np.zeros(mac.size, np.int64))
                yield EventBlock(mac, mic, np.zeros(mac.size, np.int8),
                                 h5.read(d, source, sel).astype(np.int16))

    return info, open_blocks


def write_photon_hdf5_events(path: str | os.PathLike, timestamps, detectors, *,
                             timestamps_unit: float, nanotimes=None, tcspc_unit: float = 0.0,
                             tcspc_num_bins: int = 0, laser_repetition_rate: float = 0.0,
                             description: str = "mems-stereo events"):
    """Write a minimal single-spot Photon-HDF5 file with h5py (tests, samples).

    Only the fields :func:`photon_hdf5_stream` reads, plus identity; for a
    file that passes phconvert's validation use ``phconvert.hdf5.save_photon_hdf5``.
    """
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("description", data=description)
        f.create_dataset("identity/format_name", data="Photon-HDF5")
        f.create_dataset("identity/format_version", data="0.5")
        f.create_dataset("photon_data/timestamps", data=np.asarray(timestamps, np.int64))
        f.create_dataset("photon_data/timestamps_specs/timestamps_unit",
                         data=float(timestamps_unit))
        f.create_dataset("photon_data/detectors", data=np.asarray(detectors, np.uint8))
        if nanotimes is not None:
            f.create_dataset("photon_data/nanotimes", data=np.asarray(nanotimes, np.uint16))
            f.create_dataset("photon_data/nanotimes_specs/tcspc_unit", data=float(tcspc_unit))
            f.create_dataset("photon_data/nanotimes_specs/tcspc_num_bins",
                             data=int(tcspc_num_bins))
            f.create_dataset("photon_data/measurement_specs/laser_repetition_rate",
                             data=float(laser_repetition_rate))
    return path
