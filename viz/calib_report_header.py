"""The header a filed calibration report carries: when, with what, on which device, by whom.

:func:`report_header` gives the header as a JSON-able dict (the JSON report's
``header`` object and page 1 of the PDF, through :func:`header_lines`):

================ ===========================================================
key              meaning
================ ===========================================================
date_utc         when the report was made, ISO 8601 UTC (``2026-11-27T09:14:03Z``)
package          ``"mems-stereo"``
version          the package version (``mems_stereo.__version__``)
device_id        the system JSON's ``device_id`` (None when it has none)
operator         ``calibrate --operator NAME`` (None when not given)
inputs           one object per input file: ``role`` (recording, system,
                 distances), ``path`` (as given), ``bytes``, ``sha256`` (hex)
================ ===========================================================
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from pathlib import Path

from mems_stereo.errors import MemsStereoError

#: bytes read at a time when hashing an input
_CHUNK = 1 << 20


def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, lowercase hex (64 characters), read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def utc_now_iso(now: _dt.datetime | None = None) -> str:
    """ISO 8601 UTC to the second with a ``Z``: ``2026-11-27T09:14:03Z``."""
    t = now or _dt.datetime.now(_dt.timezone.utc)
    return t.astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def report_header(inputs=(), *, device_id: str | None = None, operator: str | None = None,
                  now: _dt.datetime | None = None) -> dict:
    """The report's header (the keys of the module's table).

    inputs : (role, path) pairs, e.g. ``[("recording", "calib_1.5m.h5"),
    ("distances", "calib_distances.json")]``; a path that is not an existing
    file (a preset name) is listed with ``bytes`` and ``sha256`` None.
    device_id : the system's ``device_id``; operator : who ran it; now : the
    time to record (default: the current UTC time).
    """
    from mems_stereo import __version__

    files = []
    for role, path in inputs:
        p = Path(str(path))
        is_file = p.is_file()
        files.append({"role": str(role), "path": str(path),
                      "bytes": p.stat().st_size if is_file else None,
                      "sha256": sha256_file(p) if is_file else None})
    return {"date_utc": utc_now_iso(now), "package": "mems-stereo", "version": __version__,
            "device_id": device_id, "operator": operator, "inputs": files}


def _nominal_system(recording, system_spec):
    """``system_spec`` (file or preset), else the recording's system; None when unreadable
    (the header then has no device id: the calibration's own error says why)."""
    from mems_stereo.io.recording import read_system
    from mems_stereo.io.recording2d import is_two_axis_recording, read_recording_2d
    from mems_stereo.model.system import resolve_system

    try:
        if system_spec:
            return resolve_system(system_spec)
        if is_two_axis_recording(recording):
            return read_recording_2d(recording, truth=False).system
        return read_system(recording)
    except (MemsStereoError, OSError, ValueError):
        return None


def calibration_header(recordings, *, system_spec=None, distances_file=None,
                       operator: str | None = None, system=None) -> dict:
    """The header of a calibration's report (``calibrate --report``): the recordings,
    the system file (``system_spec`` when it is a file; a preset is listed by name)
    and the distances file with their SHA-256, ``operator``, and the ``device_id``
    of ``system`` (default: ``system_spec``'s, else the first recording's)."""
    inputs = [("recording", r) for r in recordings]
    if system_spec:
        inputs.append(("system", system_spec))
    if distances_file:
        inputs.append(("distances", distances_file))
    if system is None and recordings:
        system = _nominal_system(recordings[0], system_spec)
    return report_header(inputs, device_id=getattr(system, "device_id", None),
                         operator=operator)


def header_lines(h: dict) -> list[str]:
    """Page 1's header block: one line per field, one per input file (name, size, hash)."""
    lines = [f"date (UTC)  {h['date_utc']}",
             f"software    {h['package']} {h['version']}",
             f"device      {h['device_id'] or '— (no device_id in the system JSON)'}",
             f"operator    {h['operator'] or '— (calibrate --operator NAME)'}"]
    for f in h["inputs"]:
        size = f"{f['bytes']} B" if f["bytes"] is not None else "not a file"
        lines.append(f"{f['role']:<11} {Path(f['path']).name} ({size})")
        if f["sha256"]:
            lines.append(f"{'':11} sha256 {f['sha256']}")
    return lines
