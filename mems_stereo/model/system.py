"""The system description of FORMAT v1: load, validate, save, presets.

A :class:`System` holds every parameter of the scanner–receiver pair; it is
the one source of parameters for every stage of the package.  All values are
SI (metres, seconds, hertz, radians); the world frame is the receiver camera
frame in the OpenCV convention (see ``docs/conventions.md``).

The JSON form is ``{"format": "mems-stereo/system", "version": 1, ...}`` as
specified in ``docs/formats.md``.  Validation errors are
:class:`~mems_stereo.errors.FormatError` naming the file, the dotted field,
what was expected and what was found.
"""

from __future__ import annotations

import copy
import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mems_stereo.errors import FormatError, UnknownNameError
from mems_stereo.util.jsonfile import FieldChecker, parse_json, read_json_file

FORMAT_NAME = "mems-stereo/system"
FORMAT_VERSION = 1
ALLOWED_DIST_LENGTHS = (4, 5, 8, 12, 14)


@dataclass(frozen=True)
class Receiver:
    """OpenCV intrinsics of the SPAD receiver.

    Attributes
    ----------
    camera_matrix : (3, 3) float64, pixels
    dist_coeffs : (D,) float64, D in {4, 5, 8, 12, 14}
    image_size : (width, height) in pixels
    pixel_pitch : (2,) float64, metres (x, y)
    spad_diameter : float, metres (photosensitive diameter of one SPAD)
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]
    pixel_pitch: np.ndarray
    spad_diameter: float

    @property
    def width(self) -> int:
        return int(self.image_size[0])

    @property
    def height(self) -> int:
        return int(self.image_size[1])


@dataclass(frozen=True)
class Scanner:
    """The resonant MEMS transmitter.

    Attributes
    ----------
    position : (3,) float64, metres, world frame: the mirror pivot (baseline)
    normal_basis : (2, 3) float64, orthonormal [e1, e2]; n(θ) = cos θ e1 + sin θ e2
    laser_direction : (3,) float64, unit vector of the beam arriving at the mirror
    theta0 : float, rad, rest angle of the mirror (θ = θ0 + θ_mech)
    f_mech : float, Hz, nominal mechanical frequency
    theta_mech_max : float, rad, mechanical amplitude
    phase_offset : float, rad, delay of the true phase behind the phase of the
        zero-crossing monitor (added field, default 0; estimated by calibration)
    axis2 : optional second mirror axis (:class:`mems_stereo.model.scanner2d.Axis2`,
        JSON ``scanner.axis2``); None for the one-axis scanner of version 1
    """

    position: np.ndarray
    normal_basis: np.ndarray
    laser_direction: np.ndarray
    theta0: float
    f_mech: float
    theta_mech_max: float
    phase_offset: float = 0.0
    axis2: Any = None


@dataclass(frozen=True)
class Laser:
    """Pulsed laser: repetition rate (Hz), pulse FWHM (s), wavelength (m)."""

    f_rep: float
    pulse_fwhm: float
    wavelength: float


@dataclass(frozen=True)
class TDC:
    """Time-to-digital converter: code N in 1..n_bins has
    ``t_TOF = (N - 1/2) * bin_width - offset`` (seconds)."""

    bin_width: float
    n_bins: int
    offset: float = 0.0


@dataclass(frozen=True)
class System:
    """The whole scanner–receiver pair (FORMAT v1 system description)."""

    receiver: Receiver
    scanner: Scanner
    laser: Laser
    tdc: TDC
    speed_of_light: float = 299704644.5
    calibration: dict | None = field(default=None, compare=False)

    def __repr__(self) -> str:
        sc, rc = self.scanner, self.receiver
        b = np.asarray(sc.position, dtype=np.float64) * 1e3
        cal = ", calibrated" if self.calibration else ""
        return (f"<System {rc.width}x{rc.height} px receiver, baseline ({b[0]:.4g}, {b[1]:.4g}, "
                f"{b[2]:.4g}) mm, theta0 {sc.theta0 * 1e3:.4g} mrad, "
                f"f_mech {sc.f_mech:g} Hz, f_rep {self.laser.f_rep:g} Hz, "
                f"TDC {self.tdc.n_bins} x {self.tdc.bin_width * 1e12:.4g} ps{cal}>")

    @property
    def baseline(self) -> np.ndarray:
        """(3,) float64, metres: scanner position minus projection centre (origin)."""
        return np.asarray(self.scanner.position, dtype=np.float64)

    def replace(self, **changes: Any) -> System:
        """Copy with top-level fields replaced (``dataclasses.replace``)."""
        return replace(self, **changes)

    def with_params(self, **params: float) -> System:
        """Copy with named scalar parameters changed.

        Known names: ``theta0``, ``theta_mech_max``, ``phase_offset``,
        ``f_mech``, ``tdc_offset``, ``baseline_x``, ``baseline_y``,
        ``baseline_z``, ``fx``, ``cx``.
        """
        sc, tdc, rc = self.scanner, self.tdc, self.receiver
        pos = np.array(sc.position, dtype=np.float64)
        K = np.array(rc.camera_matrix, dtype=np.float64)
        sc_kw: dict[str, Any] = {}
        for name, value in params.items():
            value = float(value)
            if name in ("theta0", "theta_mech_max", "phase_offset", "f_mech"):
                sc_kw[name] = value
            elif name == "tdc_offset":
                tdc = replace(tdc, offset=value)
            elif name in ("baseline_x", "baseline_y", "baseline_z"):
                pos["xyz".index(name[-1])] = value
            elif name == "fx":
                K[0, 0] = value
            elif name == "cx":
                K[0, 2] = value
            else:
                raise UnknownNameError(f"unknown system parameter {name!r}")
        sc = replace(sc, position=pos, **sc_kw)
        rc = replace(rc, camera_matrix=K)
        return replace(self, scanner=sc, tdc=tdc, receiver=rc)

    def get_param(self, name: str) -> float:
        """Value of a named scalar parameter (names as in :meth:`with_params`)."""
        if name in ("theta0", "theta_mech_max", "phase_offset", "f_mech"):
            return float(getattr(self.scanner, name))
        if name == "tdc_offset":
            return float(self.tdc.offset)
        if name in ("baseline_x", "baseline_y", "baseline_z"):
            return float(self.scanner.position["xyz".index(name[-1])])
        if name == "fx":
            return float(self.receiver.camera_matrix[0, 0])
        if name == "cx":
            return float(self.receiver.camera_matrix[0, 2])
        raise UnknownNameError(f"unknown system parameter {name!r}")


# --------------------------------------------------------------------------
# validation helpers


def validate_camera_matrix(K: Any, fld: str = "camera_matrix", source: str = "") -> np.ndarray:
    """Check an OpenCV camera matrix: (3, 3), finite, fx, fy > 0, last row [0, 0, 1]."""
    ctx = FieldChecker(source)
    K = ctx.array(K, fld, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ctx.fail(fld, f"expected positive focal lengths fx, fy, found {K[0, 0]}, {K[1, 1]}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ctx.fail(fld, f"expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], found {K.tolist()}")
    if K[0, 1] != 0.0:
        raise ctx.fail(fld, f"expected zero skew K[0][1] (OpenCV's camera model has none), "
                            f"found {K[0, 1]!r}")
    return K


def validate_normal_basis(basis: Any, fld: str = "scanner.normal_basis", source: str = "",
                          tol: float = 1e-6) -> np.ndarray:
    """Check the mirror's normal basis [e1, e2]: (2, 3), unit, orthogonal."""
    ctx = FieldChecker(source)
    B = ctx.array(basis, fld, (2, 3))
    norms = np.linalg.norm(B, axis=1)
    for i in range(2):
        if abs(norms[i] - 1.0) > tol:
            raise ctx.fail(f"{fld}[{i}]", f"expected a unit vector, found norm {norms[i]:.9g}")
    dot = float(B[0] @ B[1])
    if abs(dot) > tol:
        raise ctx.fail(fld, f"expected orthogonal vectors e1, e2, found e1·e2 = {dot:.6g} "
                            "(degenerate basis)")
    return B


def system_from_dict(d: dict, source: str = "<dict>") -> System:
    """Build and validate a :class:`System` from its FORMAT v1 JSON object."""
    ctx = FieldChecker(source)
    if not isinstance(d, dict):
        raise ctx.fail("(top level)", f"expected a JSON object, found {type(d).__name__}")
    fmt = ctx.req(d, "format", "")
    if fmt != FORMAT_NAME:
        raise ctx.fail("format", f"expected {FORMAT_NAME!r}, found {fmt!r}")
    ver = ctx.req(d, "version", "")
    if isinstance(ver, bool) or not isinstance(ver, int) or ver != FORMAT_VERSION:
        raise ctx.fail("version", f"expected {FORMAT_VERSION}, found {ver!r}")

    r = ctx.req(d, "receiver", "")
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
    receiver = Receiver(K, dist, (int(size[0]), int(size[1])), pitch, spad)

    s = ctx.req(d, "scanner", "")
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
        from mems_stereo.model.scanner2d import axis2_from_dict

        scanner = replace(scanner, axis2=axis2_from_dict(s["axis2"], scanner, source))

    la = ctx.req(d, "laser", "")
    laser = Laser(
        f_rep=ctx.number(ctx.req(la, "f_rep", "laser"), "laser.f_rep", positive=True),
        pulse_fwhm=ctx.number(ctx.req(la, "pulse_fwhm", "laser"), "laser.pulse_fwhm",
                              nonneg=True),
        wavelength=ctx.number(ctx.req(la, "wavelength", "laser"), "laser.wavelength",
                              positive=True),
    )

    t = ctx.req(d, "tdc", "")
    n_bins = ctx.req(t, "n_bins", "tdc")
    if isinstance(n_bins, bool) or not isinstance(n_bins, int) or not 1 <= n_bins <= 65535:
        raise ctx.fail("tdc.n_bins", f"expected an integer in 1..65535, found {n_bins!r}")
    tdc = TDC(
        bin_width=ctx.number(ctx.req(t, "bin_width", "tdc"), "tdc.bin_width", positive=True),
        n_bins=n_bins,
        offset=ctx.number(t.get("offset", 0.0), "tdc.offset"),
    )
    c = ctx.number(ctx.req(d, "speed_of_light", ""), "speed_of_light", positive=True)
    calib = d.get("calibration")
    if calib is not None and not isinstance(calib, dict):
        raise ctx.fail("calibration", f"expected an object, found {type(calib).__name__}")
    system = System(receiver, scanner, laser, tdc, c, copy.deepcopy(calib))
    check_plausible(system, source)
    return system


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


def check_plausible(system: System, source: str = "<dict>") -> None:
    """Refuse physically implausible values (bounds: :data:`PLAUSIBLE`).

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


def system_to_dict(system: System) -> dict:
    """The FORMAT v1 JSON object of a :class:`System`."""
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
        from mems_stereo.model.scanner2d import axis2_to_dict

        d["scanner"]["axis2"] = axis2_to_dict(s.axis2)
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
    """Read and validate a system description JSON file."""
    return system_from_dict(read_json_file(path), source=str(Path(path)))


def save_system(system: System, path: str | os.PathLike) -> Path:
    """Write a system description JSON atomically (temporary file, then rename)."""
    from mems_stereo.util.atomic import atomic_write_text

    return atomic_write_text(path, system_to_json(system) + "\n")


# --------------------------------------------------------------------------
# presets


def theta0_for_working_distance(baseline_x: float, working_distance: float) -> float:
    """Exact θ0 (rad) making the transmitter axis cross the optical axis at W.

    θ0 = π/4 − ½·atan(x_M0 / W); compare :func:`mems_stereo.model.scanner.theta0_small_angle`.
    """
    return math.pi / 4 - 0.5 * math.atan(baseline_x / working_distance)


def burkard2022(working_distance: float = 2.5) -> System:
    """The proof-of-concept system of Burkard et al. 2022, Table 1.

    SPADEye2 line (192 x 1 pixels, w = 40.56 µm, h = 209.6 µm, 12 µm SPADs),
    f = 8 mm receiver optics, 12.5 cm baseline with the mirror at x = −0.125 m,
    f_mech = 1570 Hz, θ_mech,max = 11.9°, f_rep = 20 kHz, 14.9 ns pulses,
    312.5 ps TDC bins (4096 bins), θ0 from the working distance (exact form).
    """
    f = 8e-3
    w, h = 40.56e-6, 209.6e-6
    K = np.array([[f / w, 0.0, 95.5], [0.0, f / h, 0.0], [0.0, 0.0, 1.0]])
    b = 0.125
    return System(
        receiver=Receiver(K, np.zeros(5), (192, 1), np.array([w, h]), 12e-6),
        scanner=Scanner(
            position=np.array([-b, 0.0, 0.0]),
            normal_basis=np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
            laser_direction=np.array([-1.0, 0.0, 0.0]),
            theta0=theta0_for_working_distance(b, working_distance),
            f_mech=1570.0,
            theta_mech_max=math.radians(11.9),
        ),
        laser=Laser(f_rep=20000.0, pulse_fwhm=14.9e-9, wavelength=659e-9),
        tdc=TDC(bin_width=312.5e-12, n_bins=4096, offset=0.0),
        speed_of_light=299704644.5,
    )


PRESETS = {"burkard2022": burkard2022}


class UnknownPresetError(FormatError, UnknownNameError):
    """An unknown preset name (a ``FormatError``, hence ``ValueError``; also an
    :class:`~mems_stereo.errors.UnknownNameError`, hence ``KeyError`` as in
    version 0.1).  The message lists the presets."""

    def __str__(self) -> str:  # KeyError would print the message's repr
        return str(self.args[0]) if self.args else ""


def _presets_advice(name: str) -> str:
    import difflib

    close = difflib.get_close_matches(str(name), sorted(PRESETS), n=1, cutoff=0.5)
    return ((f"did you mean {close[0]!r}? " if close else "")
            + f"presets: {', '.join(sorted(PRESETS))}")


def preset(name: str) -> System:
    """A named preset system (``"burkard2022"``; :data:`PRESETS` lists them)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise UnknownPresetError(f"unknown preset {name!r}\n{_presets_advice(name)}",
                                 field="preset") from None


def resolve_system(spec: str | os.PathLike | System) -> System:
    """A System from an instance, a preset name or a JSON path.

    A string that is neither a preset nor an existing file raises
    :class:`UnknownPresetError` listing the presets (with a suggestion for a
    near miss).
    """
    if isinstance(spec, System):
        return spec
    if isinstance(spec, str) and spec in PRESETS:
        return preset(spec)
    if not Path(spec).exists():
        raise UnknownPresetError(f"{str(spec)!r} is neither a preset nor a system file\n"
                                 f"{_presets_advice(str(spec))}, or the path of a system JSON "
                                 "file", field="system")
    return load_system(spec)
