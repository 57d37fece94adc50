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

import math
import re
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
    harmonics : tuple of :class:`Harmonic`, the trajectory beyond the cosine
        (``docs/hardware.md``); empty for the ideal mirror
    monitor : :class:`MonitorEdges` or None, the monitor's edge delays (None: ideal)
    """

    position: np.ndarray
    normal_basis: np.ndarray
    laser_direction: np.ndarray
    theta0: float
    f_mech: float
    theta_mech_max: float
    phase_offset: float = 0.0
    axis2: Any = None
    harmonics: tuple = ()
    monitor: Any = None


@dataclass(frozen=True)
class Harmonic:
    """One harmonic of the mirror's trajectory (``docs/hardware.md``).

    θ_mech = θ_mech,max · (cos φ + Σ amplitude · cos(order · φ + phase)).

    order : int >= 2; amplitude : relative to θ_mech,max (0.003 = 0.3 %);
    phase : rad; amplitude_std, phase_std : σ where estimated, else None.
    """

    order: int
    amplitude: float
    phase: float = 0.0
    amplitude_std: float | None = None
    phase_std: float | None = None


@dataclass(frozen=True)
class MonitorEdges:
    """The zero-crossing monitor's delays per edge (comparator delay and hysteresis).

    A recorded rising (falling) crossing is the true zero crossing plus
    ``rising_delay`` (``falling_delay``), s; ``*_std`` σ where estimated, else None.
    """

    rising_delay: float = 0.0
    falling_delay: float = 0.0
    rising_delay_std: float | None = None
    falling_delay_std: float | None = None


@dataclass(frozen=True)
class PulseModel:
    """A pulse shape beyond the Gaussian (``docs/hardware.md``).

    Attributes
    ----------
    model : str
        ``"ex-gaussian"``: the density (1 − w)·N(0, σ) + w·EMG(σ, τ), σ from the
        laser's ``pulse_fwhm`` (delay 0 is the Gaussian core's peak), w =
        ``tail_fraction``, τ = ``tail_decay`` (s); or ``"table"``: ``times`` (m,) s
        increasing and ``power`` (m,) ≥ 0, the measured instrument response.
    tail_fraction_std, tail_decay_std : float or None
        σ where estimated, else None.
    """

    model: str = "ex-gaussian"
    tail_fraction: float = 0.0
    tail_decay: float = 0.0
    tail_fraction_std: float | None = None
    tail_decay_std: float | None = None
    times: Any = None
    power: Any = None


@dataclass(frozen=True)
class Laser:
    """Pulsed laser: repetition rate (Hz), pulse FWHM (s), wavelength (m); and an
    optional :class:`PulseModel` (None: the Gaussian of ``pulse_fwhm``)."""

    f_rep: float
    pulse_fwhm: float
    wavelength: float
    pulse_shape: Any = None


@dataclass(frozen=True)
class TDC:
    """Time-to-digital converter: code N in 1..n_bins has
    ``t_TOF = (N - 1/2) * bin_width - offset`` (seconds) for the ideal converter.

    With ``code_widths`` (n_bins,) in units of ``bin_width`` (DNL: width − 1) code
    N's centre is ``bin_width · (Σ_{i<N} w_i + w_N / 2)``; with ``pixel_offsets``
    (H·W,) s (row-major) pixel p's time is less ``pixel_offsets[p]``
    (:mod:`mems_stereo.model.tdc`).  ``*_std``: σ where estimated, else None.
    """

    bin_width: float
    n_bins: int
    offset: float = 0.0
    pixel_offsets: Any = None
    pixel_offsets_std: Any = None
    code_widths: Any = None
    code_widths_std: Any = None

    @property
    def ideal(self) -> bool:
        """No per-pixel offsets and equal code widths."""
        return self.pixel_offsets is None and self.code_widths is None


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
        cal += "" if self.ideal_hardware else ", hardware model"
        return (f"<System {rc.width}x{rc.height} px receiver, baseline ({b[0]:.4g}, {b[1]:.4g}, "
                f"{b[2]:.4g}) mm, theta0 {sc.theta0 * 1e3:.4g} mrad, "
                f"f_mech {sc.f_mech:g} Hz, f_rep {self.laser.f_rep:g} Hz, "
                f"TDC {self.tdc.n_bins} x {self.tdc.bin_width * 1e12:.4g} ps{cal}>")

    @property
    def ideal_hardware(self) -> bool:
        """True when no member of the hardware model (``docs/hardware.md``) is set:
        a cosine trajectory, equal monitor edges, a Gaussian pulse, an ideal TDC."""
        sc = self.scanner
        return (not sc.harmonics and sc.monitor is None and self.laser.pulse_shape is None
                and self.tdc.ideal)

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
        ``baseline_z``, ``fx``, ``cx``; the hardware model's (``docs/hardware.md``):
        ``harmonic{k}_cos``, ``harmonic{k}_sin``, ``edge_rising_delay``,
        ``edge_falling_delay``, ``pulse_tail_fraction``, ``pulse_tail_decay``,
        ``pixel_offset_{i}``.
        """
        sc, tdc, rc = self.scanner, self.tdc, self.receiver
        pos = np.array(sc.position, dtype=np.float64)
        K = np.array(rc.camera_matrix, dtype=np.float64)
        sc_kw: dict[str, Any] = {}
        hw: dict[str, float] = {}
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
                hw[name] = value
        sc = replace(sc, position=pos, **sc_kw)
        rc = replace(rc, camera_matrix=K)
        laser = self.laser
        for name, value in hw.items():
            sc, laser, tdc = _with_hardware_param(sc, laser, tdc, name, value, rc)
        return replace(self, scanner=sc, tdc=tdc, receiver=rc, laser=laser)

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
        return _hardware_param(self, name)


def pulse_mean_delay(laser: Laser) -> float:
    """Mean delay (s) of the pulse after its delay 0 (the Gaussian core's peak):
    0 for the Gaussian, w·τ for the ex-gaussian, the centroid of a table."""
    p = laser.pulse_shape
    if p is None:
        return 0.0
    if p.model == "table":
        t = np.asarray(p.times, dtype=np.float64)
        w = np.asarray(p.power, dtype=np.float64)
        return float(np.trapezoid(t * w, t) / np.trapezoid(w, t))
    return float(p.tail_fraction * p.tail_decay)


# --------------------------------------------------------------------------
# the hardware model's named parameters

_HARMONIC = re.compile(r"harmonic([0-9]+)_(cos|sin)")
_PIXEL = re.compile(r"pixel_offset_([0-9]+)")


def _harmonic_coefficients(sc: Scanner, order: int) -> tuple[float, float]:
    """(cos, sin) coefficients of a harmonic: A cos(kφ + ψ) = c cos kφ + s sin kφ."""
    for h in sc.harmonics:
        if h.order == order:
            return h.amplitude * math.cos(h.phase), -h.amplitude * math.sin(h.phase)
    return 0.0, 0.0


def _with_hardware_param(sc: Scanner, laser: Laser, tdc: TDC, name: str, value: float,
                         rc: Receiver):
    """(scanner, laser, tdc) with one hardware-model parameter set (names: see
    :meth:`System.with_params`)."""
    m = _HARMONIC.fullmatch(name)
    if m and int(m.group(1)) >= 2:
        k = int(m.group(1))
        c, s = _harmonic_coefficients(sc, k)
        c, s = (value, s) if m.group(2) == "cos" else (c, value)
        old = [h for h in sc.harmonics if h.order == k]
        new = (replace(old[0], amplitude=math.hypot(c, s), phase=math.atan2(-s, c)) if old
               else Harmonic(k, math.hypot(c, s), math.atan2(-s, c)))
        hs = tuple(sorted([h for h in sc.harmonics if h.order != k] + [new],
                          key=lambda h: h.order))
        return replace(sc, harmonics=hs), laser, tdc
    if name in ("edge_rising_delay", "edge_falling_delay"):
        mon = sc.monitor if sc.monitor is not None else MonitorEdges()
        mon = replace(mon, **{name[5:]: value})
        return replace(sc, monitor=mon), laser, tdc
    if name in ("pulse_tail_fraction", "pulse_tail_decay"):
        ps = laser.pulse_shape if laser.pulse_shape is not None else PulseModel()
        if ps.model != "ex-gaussian":
            raise UnknownNameError(f"{name}: the pulse is tabulated, not ex-gaussian")
        return sc, replace(laser, pulse_shape=replace(ps, **{name[6:]: value})), tdc
    m = _PIXEL.fullmatch(name)
    n_pix = rc.width * rc.height
    if m and int(m.group(1)) < n_pix:
        off = (np.zeros(n_pix) if tdc.pixel_offsets is None
               else np.array(tdc.pixel_offsets, dtype=np.float64))
        off[int(m.group(1))] = value
        return sc, laser, replace(tdc, pixel_offsets=off)
    raise UnknownNameError(f"unknown system parameter {name!r}")


def _hardware_param(system: System, name: str) -> float:
    """Value of a hardware-model parameter (0 where the member is absent)."""
    sc, laser, tdc = system.scanner, system.laser, system.tdc
    m = _HARMONIC.fullmatch(name)
    if m and int(m.group(1)) >= 2:
        c, s = _harmonic_coefficients(sc, int(m.group(1)))
        return c if m.group(2) == "cos" else s
    if name in ("edge_rising_delay", "edge_falling_delay"):
        return 0.0 if sc.monitor is None else float(getattr(sc.monitor, name[5:]))
    if name in ("pulse_tail_fraction", "pulse_tail_decay"):
        ps = laser.pulse_shape
        return 0.0 if ps is None else float(getattr(ps, name[6:]))
    m = _PIXEL.fullmatch(name)
    if m and int(m.group(1)) < system.receiver.width * system.receiver.height:
        return 0.0 if tdc.pixel_offsets is None else float(tdc.pixel_offsets[int(m.group(1))])
    raise UnknownNameError(f"unknown system parameter {name!r}")


# --------------------------------------------------------------------------
# validation helpers


def validate_camera_matrix(K: Any, fld: str = "camera_matrix", source: str = "") -> np.ndarray:
    """Check an OpenCV camera matrix: (3, 3), finite, fx, fy > 0, last row [0, 0, 1]."""
    ctx = FieldChecker(source)
    K = ctx.array(K, fld, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ctx.fail(fld, f"expected positive focal lengths fx, fy, found {K[0, 0]}, {K[1, 1]}")
    k0, k1, k2 = (float(x) for x in K[2])  # np.allclose(K[2], [0, 0, 1]), scalar by scalar
    if not (abs(k0) <= 1e-8 and abs(k1) <= 1e-8 and abs(k2 - 1.0) <= 1e-8 + 1e-5) \
            or K[1, 0] != 0.0:
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
