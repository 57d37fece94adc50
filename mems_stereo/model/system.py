"""The system description of FORMAT v1: read, validate, write; resolve a name to a system.

The JSON form is ``{"format": "mems-stereo/system", "version": 1, ...}`` as
specified in ``docs/formats.md``; the typed parameters it reads into are
:mod:`mems_stereo.model.hardware` (re-exported here, where callers know them
from) and the named systems :mod:`mems_stereo.model.presets`.  Validation
errors are :class:`~mems_stereo.errors.FormatError` naming the file, the
dotted field, what was expected and what was found.
"""

from __future__ import annotations

import copy
import json
import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mems_stereo.model.hardware import (
    ALLOWED_DIST_LENGTHS,
    TDC,
    Laser,
    Receiver,
    Scanner,
    System,
    validate_camera_matrix,
    validate_normal_basis,
)
from mems_stereo.model.hardware_json import hardware_from_dict, hardware_to_dict
from mems_stereo.model.presets import (
    PRESETS,
    UnknownPresetError,
    burkard2022,
    presets_advice,
    system_source,
    theta0_for_working_distance,
)
from mems_stereo.model.scanner2d import axis2_from_dict, axis2_to_dict
from mems_stereo.util.atomic import atomic_write_text
from mems_stereo.util.jsonfile import FieldChecker, check_schema, parse_json, read_json_file
from mems_stereo.util.schemas import SYSTEM_FIELDS

__all__ = [
    "ALLOWED_DIST_LENGTHS", "FORMAT_NAME", "FORMAT_VERSION", "PLAUSIBLE", "PRESETS", "TDC",
    "Laser", "Receiver", "Scanner", "System", "UnknownPresetError", "burkard2022",
    "check_plausible", "load_system", "preset", "resolve_any_system", "resolve_system",
    "save_system", "system_from_dict", "system_from_json", "system_to_dict", "system_to_json",
    "theta0_for_working_distance", "validate_camera_matrix", "validate_normal_basis",
]

FORMAT_NAME = "mems-stereo/system"
FORMAT_VERSION = 1


def system_from_dict(d: dict, source: str = "<dict>") -> System:
    """Build and validate a :class:`System` from its FORMAT v1 JSON object.

    Examples
    --------
    >>> d = ms.system_to_dict(ms.preset("burkard2022"))
    >>> ms.system_from_dict(d).tdc.n_bins
    4096
    >>> try:
    ...     ms.system_from_dict({"version": 1})
    ... except ms.FormatError as err:
    ...     print(err)
    <dict>: format: required field is missing
    """
    ctx = FieldChecker(source)
    if not isinstance(d, dict):
        raise ctx.fail("(top level)", f"expected a JSON object, found {type(d).__name__}")
    check_schema(d, SYSTEM_FIELDS, ctx)  # format, version, members and types
    receiver = _receiver_from_dict(ctx.req(d, "receiver", ""), ctx, source)
    scanner = _scanner_from_dict(ctx.req(d, "scanner", ""), ctx, source)
    laser = _laser_from_dict(ctx.req(d, "laser", ""), ctx)
    tdc = _tdc_from_dict(ctx.req(d, "tdc", ""), ctx)
    c = ctx.number(ctx.req(d, "speed_of_light", ""), "speed_of_light", positive=True)
    calib = d.get("calibration")
    if calib is not None and not isinstance(calib, dict):
        raise ctx.fail("calibration", f"expected an object, found {type(calib).__name__}")
    device = d.get("device_id")
    if device is not None and (not isinstance(device, str) or not device.strip()):
        raise ctx.fail("device_id", f"expected a non-empty string, found {device!r}")
    scanner, laser, tdc = hardware_from_dict(d, receiver, scanner, laser, tdc, ctx)
    system = System(receiver, scanner, laser, tdc, c, copy.deepcopy(calib), device_id=device)
    check_plausible(system, source)
    return system


def _receiver_from_dict(r: Any, ctx: FieldChecker, source: str) -> Receiver:
    K = validate_camera_matrix(ctx.req(r, "camera_matrix", "receiver"),
                               "receiver.camera_matrix", source)
    dist = ctx.array(ctx.req(r, "dist_coeffs", "receiver"), "receiver.dist_coeffs", (None,))
    if dist.size not in ALLOWED_DIST_LENGTHS:
        raise ctx.fail("receiver.dist_coeffs",
                       f"expected 4, 5, 8, 12 or 14 coefficients, found {dist.size}")
    size = ctx.req(r, "image_size", "receiver")
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise ctx.fail("receiver.image_size",
                       f"expected [width, height] as two positive integers, found {size!r}")
    pitch = ctx.array(ctx.req(r, "pixel_pitch", "receiver"), "receiver.pixel_pitch", (2,))
    if np.any(pitch <= 0):
        raise ctx.fail("receiver.pixel_pitch", f"expected positive values, found {pitch.tolist()}")
    spad = ctx.number(ctx.req(r, "spad_diameter", "receiver"), "receiver.spad_diameter",
                      positive=True)
    return Receiver(K, dist, (int(size[0]), int(size[1])), pitch, spad)


def _scanner_from_dict(s: Any, ctx: FieldChecker, source: str) -> Scanner:
    pos = ctx.array(ctx.req(s, "position", "scanner"), "scanner.position", (3,))
    basis = validate_normal_basis(ctx.req(s, "normal_basis", "scanner"),
                                  "scanner.normal_basis", source)
    dl = ctx.array(ctx.req(s, "laser_direction", "scanner"), "scanner.laser_direction", (3,))
    if abs(np.linalg.norm(dl) - 1.0) > 1e-6:
        raise ctx.fail("scanner.laser_direction",
                       f"expected a unit vector, found norm {np.linalg.norm(dl):.9g}")
    scanner = Scanner(
        position=pos,
        normal_basis=basis,
        laser_direction=dl,
        theta0=ctx.number(ctx.req(s, "theta0", "scanner"), "scanner.theta0"),
        f_mech=ctx.number(ctx.req(s, "f_mech", "scanner"), "scanner.f_mech", positive=True),
        theta_mech_max=ctx.number(ctx.req(s, "theta_mech_max", "scanner"),
                                  "scanner.theta_mech_max", positive=True),
        phase_offset=ctx.number(s.get("phase_offset", 0.0), "scanner.phase_offset"),
    )
    if s.get("axis2") is not None:  # two-axis extension (docs/two_axis.md)
        scanner = replace(scanner, axis2=axis2_from_dict(s["axis2"], scanner, source))
    return scanner


def _laser_from_dict(la: Any, ctx: FieldChecker) -> Laser:
    return Laser(
        f_rep=ctx.number(ctx.req(la, "f_rep", "laser"), "laser.f_rep", positive=True),
        pulse_fwhm=ctx.number(ctx.req(la, "pulse_fwhm", "laser"), "laser.pulse_fwhm",
                              nonneg=True),
        wavelength=ctx.number(ctx.req(la, "wavelength", "laser"), "laser.wavelength",
                              positive=True),
    )


def _tdc_from_dict(t: Any, ctx: FieldChecker) -> TDC:
    n_bins = ctx.req(t, "n_bins", "tdc")
    if isinstance(n_bins, bool) or not isinstance(n_bins, int) or not 1 <= n_bins <= 65535:
        raise ctx.fail("tdc.n_bins", f"expected an integer in 1..65535, found {n_bins!r}")
    return TDC(
        bin_width=ctx.number(ctx.req(t, "bin_width", "tdc"), "tdc.bin_width", positive=True),
        n_bins=n_bins,
        offset=ctx.number(t.get("offset", 0.0), "tdc.offset"),
    )


#: Physical plausibility bounds (inclusive) of the system description, in SI
#: units: a value outside is refused on read (docs/reliability.md).  They are
#: wide (orders of magnitude around the paper's system) and exist so that a
#: typo cannot make the package allocate gigabytes (``theta_mech_max`` = 1e3,
#: ``pulse_fwhm`` = 1 s) or return an empty cloud with exit 0 (c = 1 m/s).
PLAUSIBLE: dict[str, tuple[float, float]] = {
    "receiver.image_size.width": (1, 4096),
    "receiver.image_size.height": (1, 4096),
    "receiver.pixels": (1, 1 << 20),
    "receiver.camera_matrix.fx": (1.0, 1e6),
    "receiver.camera_matrix.fy": (1.0, 1e6),
    "receiver.pixel_pitch": (1e-7, 1e-2),
    "receiver.spad_diameter": (1e-7, 1e-2),
    "scanner.position": (-100.0, 100.0),
    "scanner.theta0": (-math.pi / 2, math.pi / 2),
    "scanner.f_mech": (1e-3, 1e6),
    "scanner.theta_mech_max": (1e-6, math.pi / 4),
    "laser.f_rep": (1.0, 1e9),
    "laser.pulse_fwhm": (0.0, 1e-6),
    "laser.wavelength": (1e-7, 1e-4),
    "tdc.bin_width": (1e-13, 1e-6),
    "tdc.offset": (-1e-3, 1e-3),
    "tdc.range": (1e-10, 1e-2),
    "speed_of_light": (2.9e8, 3.0e8),
}


#: shortest accepted baseline ``|scanner.position|`` (m): below it the mirror sits at
#: the receiver's projection centre and no depth can be triangulated
MIN_BASELINE = 1e-3


def check_plausible(system: System, source: str = "<dict>") -> None:
    """Refuse physically implausible values (bounds: :data:`PLAUSIBLE`; a baseline
    shorter than :data:`MIN_BASELINE`).

    Raises :class:`~mems_stereo.errors.FormatError` naming the field, the value
    and the bounds.
    """
    r, s, la, t = system.receiver, system.scanner, system.laser, system.tdc
    K = np.asarray(r.camera_matrix, float)
    values = {
        "receiver.image_size.width": r.image_size[0],
        "receiver.image_size.height": r.image_size[1],
        "receiver.pixels": r.image_size[0] * r.image_size[1],
        "receiver.camera_matrix.fx": K[0, 0],
        "receiver.camera_matrix.fy": K[1, 1],
        "receiver.pixel_pitch": np.asarray(r.pixel_pitch, float),
        "receiver.spad_diameter": r.spad_diameter,
        "scanner.position": np.asarray(s.position, float),
        "scanner.theta0": s.theta0,
        "scanner.f_mech": s.f_mech,
        "scanner.theta_mech_max": s.theta_mech_max,
        "laser.f_rep": la.f_rep,
        "laser.pulse_fwhm": la.pulse_fwhm,
        "laser.wavelength": la.wavelength,
        "tdc.bin_width": t.bin_width,
        "tdc.offset": t.offset,
        "tdc.range": t.n_bins * t.bin_width,
        "speed_of_light": system.speed_of_light,
    }
    ctx = FieldChecker(source)
    for name, v in values.items():
        lo, hi = PLAUSIBLE[name]
        a = np.atleast_1d(np.asarray(v, dtype=float))
        if not (np.all(a >= lo) and np.all(a <= hi)):
            shown = a.tolist() if a.size > 1 else float(a[0])
            raise ctx.fail(name, f"expected a physically plausible value in [{lo:g}, {hi:g}], "
                                 f"found {shown!r}")
    baseline = float(np.linalg.norm(np.asarray(s.position, float)))
    if baseline < MIN_BASELINE:  # the mirror at the projection centre: nothing to triangulate
        raise ctx.fail("scanner.position", f"expected the mirror away from the receiver's "
                                           f"projection centre (a baseline of at least "
                                           f"{MIN_BASELINE * 1e3:g} mm), found a baseline of "
                                           f"{baseline * 1e3:.3g} mm: no depth by triangulation")


def system_to_dict(system: System) -> dict:
    """The FORMAT v1 JSON object of a :class:`System`.

    Examples
    --------
    >>> d = ms.system_to_dict(ms.preset("burkard2022"))
    >>> sorted(d)
    ['format', 'laser', 'receiver', 'scanner', 'speed_of_light', 'tdc', 'version']
    >>> d["tdc"]["n_bins"]
    4096
    """
    r, s, la, t = system.receiver, system.scanner, system.laser, system.tdc
    d: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "receiver": {
            "camera_matrix": np.asarray(r.camera_matrix, float).tolist(),
            "dist_coeffs": np.asarray(r.dist_coeffs, float).tolist(),
            "image_size": [int(r.image_size[0]), int(r.image_size[1])],
            "pixel_pitch": np.asarray(r.pixel_pitch, float).tolist(),
            "spad_diameter": float(r.spad_diameter),
        },
        "scanner": {
            "position": np.asarray(s.position, float).tolist(),
            "normal_basis": np.asarray(s.normal_basis, float).tolist(),
            "laser_direction": np.asarray(s.laser_direction, float).tolist(),
            "theta0": float(s.theta0),
            "f_mech": float(s.f_mech),
            "theta_mech_max": float(s.theta_mech_max),
        },
        "laser": {"f_rep": float(la.f_rep), "pulse_fwhm": float(la.pulse_fwhm),
                  "wavelength": float(la.wavelength)},
        "tdc": {"bin_width": float(t.bin_width), "n_bins": int(t.n_bins),
                "offset": float(t.offset)},
        "speed_of_light": float(system.speed_of_light),
    }
    if s.phase_offset != 0.0:
        d["scanner"]["phase_offset"] = float(s.phase_offset)
    if s.axis2 is not None:  # two-axis extension (docs/two_axis.md)
        d["scanner"]["axis2"] = axis2_to_dict(s.axis2)
    hardware_to_dict(s, la, t, d)  # the hardware model's members (docs/hardware.md)
    if system.device_id is not None:
        d["device_id"] = str(system.device_id)
    if system.calibration is not None:
        d["calibration"] = copy.deepcopy(system.calibration)
    return d


def system_from_json(text: str, source: str = "<string>") -> System:
    """Parse and validate a system description from JSON text."""
    return system_from_dict(parse_json(text, source), source)


def system_to_json(system: System) -> str:
    """JSON text of a :class:`System` (indented, stable key order)."""
    return json.dumps(system_to_dict(system), indent=2)


def load_system(path: str | os.PathLike) -> System:
    """Read and validate a system description JSON file.

    Examples
    --------
    >>> system = ms.load_system(ms.data.path("nominal_system.json"))
    >>> system.receiver.image_size, system.scanner.f_mech
    ((192, 1), 1570.0)
    """
    return system_from_dict(read_json_file(path), source=str(Path(path)))


def save_system(system: System, path: str | os.PathLike) -> Path:
    """Write a system description JSON atomically (temporary file, then rename).

    Examples
    --------
    >>> import os, tempfile
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = ms.save_system(ms.preset("burkard2022"), os.path.join(folder, "system.json"))
    ...     print(path.name, ms.load_system(path).tdc.n_bins)
    system.json 4096
    """
    return atomic_write_text(path, system_to_json(system) + "\n")


# --------------------------------------------------------------------------
# resolving a name or a path


def preset(name: str) -> System:
    """A named preset system (:data:`PRESETS` lists them, one- and two-axis).

    Examples
    --------
    >>> sorted(ms.PRESETS)
    ['burkard2022', 'lissajous64', 'raster128x96']
    >>> ms.preset("burkard2022")  # doctest: +NORMALIZE_WHITESPACE
    <System 192x1 px receiver, baseline (-125, 0, 0) mm, theta0 760.4 mrad, f_mech 1570 Hz,
     f_rep 20000 Hz, TDC 4096 x 312.5 ps>
    """
    try:
        return PRESETS[name]()
    except (KeyError, TypeError):
        raise UnknownPresetError(f"unknown preset {name!r}\n{presets_advice(str(name))}",
                                 field="preset") from None


def resolve_system(spec: str | os.PathLike | System) -> System:
    """A System from an instance, an existing JSON file or a preset name (one- or
    two-axis), in that order (:func:`~mems_stereo.model.presets.system_source`).

    Anything else raises :class:`UnknownPresetError`: a path that does not exist
    as ``FILE: not found`` advising the nearest file of its folder, a name that is
    no preset advising the nearest preset.
    """
    if isinstance(spec, System):
        return spec
    src = system_source(spec)
    return preset(src) if isinstance(src, str) else load_system(src)


#: the same as :func:`resolve_system` (every preset resolves through one registry)
resolve_any_system = resolve_system
