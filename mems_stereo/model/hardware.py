"""The hardware of the scanner–receiver pair as typed parameters.

A :class:`System` holds every parameter of the pair: the SPAD receiver
(:class:`Receiver`), the MEMS transmitter (:class:`Scanner`), the laser
(:class:`Laser`) and the time-to-digital converter (:class:`TDC`).  All values
are SI (metres, seconds, hertz, radians); the world frame is the receiver
camera frame in the OpenCV convention (see ``docs/conventions.md``).  Reading
and writing the JSON form is :mod:`mems_stereo.model.system`; named systems
are :mod:`mems_stereo.model.presets`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mems_stereo.errors import UnknownNameError
from mems_stereo.util.jsonfile import FieldChecker

#: lengths of an OpenCV distortion vector
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
    """The whole scanner–receiver pair (FORMAT v1 system description).

    Examples
    --------
    >>> system = ms.preset("burkard2022")
    >>> system.receiver.image_size, system.tdc.n_bins, system.tdc.bin_width
    ((192, 1), 4096, 3.125e-10)
    >>> system.baseline          # scanner position, receiver camera frame, m
    array([-0.125,  0.   ,  0.   ])
    """

    receiver: Receiver
    scanner: Scanner
    laser: Laser
    tdc: TDC
    speed_of_light: float = 299704644.5
    calibration: dict | None = field(default=None, compare=False)
    #: the hardware's identifier (serial number, asset tag; JSON ``device_id``), or None
    device_id: str | None = field(default=None, compare=False)

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
