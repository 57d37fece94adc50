"""Named systems: the paper's one-axis system and two two-axis examples, in one registry.

Each preset is a function returning a :class:`~mems_stereo.model.hardware.System`;
:data:`PRESETS` maps every preset's name to it (one- and two-axis), the subsets
:data:`ONE_AXIS_PRESETS` and :data:`TWO_AXIS_PRESETS` the names of each kind.
What a system argument names (an existing file, else a preset, else an error
that says which file is missing or which preset was meant) is
:func:`system_source`; every command's ``--system`` and
:func:`mems_stereo.model.system.resolve_system` go through it.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError, UnknownNameError
from mems_stereo.model.hardware import TDC, Laser, Receiver, Scanner, System
from mems_stereo.model.scanner2d import Axis2, fast_axis
from mems_stereo.util.jsonfile import closest_key


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


def outer_axis_for(scanner: Scanner) -> np.ndarray:
    """The natural outer axis: in the mirror plane at rest, perpendicular to a1,
    ``a2 = a1 × n1(θ0)``; turning about it tilts the beam out of the fast scan plane."""
    B = np.asarray(scanner.normal_basis, float)
    n0 = math.cos(scanner.theta0) * B[0] + math.sin(scanner.theta0) * B[1]
    a2 = np.cross(fast_axis(scanner), n0)
    return a2 / np.linalg.norm(a2)


#: link budget of the two-axis presets (LinkBudget keyword arguments): a short-pulse
#: diode and a 2-D SPAD array with microlenses (fill factor 0.5), f = 6 mm, f/2
TWO_AXIS_LINK = {"peak_power": 1.0, "focal_length": 6e-3, "f_number": 2.0, "fill_factor": 0.5}


def square_pixel_receiver(width: int, height: int, pitch: float, f: float) -> Receiver:
    """A distortion-free receiver of ``width`` × ``height`` square pixels of ``pitch``
    metres behind a lens of focal length ``f`` metres, principal point at the centre,
    25 µm SPADs."""
    K = np.array([[f / pitch, 0.0, (width - 1) / 2], [0.0, f / pitch, (height - 1) / 2],
                  [0.0, 0.0, 1.0]])
    return Receiver(K, np.zeros(5), (width, height), np.array([pitch, pitch]), 25e-6)


def two_axis_system(receiver: Receiver, mode: str, f1: float, amp1: float, f2: float,
                    amp2: float, f_rep: float, working_distance: float = 2.5) -> System:
    """A two-axis system on the paper's 12.5 cm baseline.

    ``mode`` is axis 2's mode ("resonant" or "quasistatic"); ``f1``, ``amp1`` the
    fast axis' frequency (Hz) and mechanical amplitude (rad), ``f2``, ``amp2`` axis
    2's; ``f_rep`` the shot rate (Hz); θ0 makes the transmitter axis cross the
    optical axis at ``working_distance`` metres.  Axis 2 turns about
    :func:`outer_axis_for` the fast axis; 0.3 ns pulses at 905 nm, 100 ps TDC bins
    (1024).
    """
    b = 0.125
    sc = Scanner(position=np.array([-b, 0.0, 0.0]),
                 normal_basis=np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                 laser_direction=np.array([-1.0, 0.0, 0.0]),
                 theta0=theta0_for_working_distance(b, working_distance),
                 f_mech=f1, theta_mech_max=amp1)
    a2 = Axis2(mode=mode, axis=outer_axis_for(sc), theta0=0.0, f_mech=f2, theta_mech_max=amp2)
    sc = replace(sc, axis2=a2)
    return System(
        receiver=receiver,
        scanner=sc,
        laser=Laser(f_rep=f_rep, pulse_fwhm=0.3e-9, wavelength=905e-9),
        tdc=TDC(bin_width=100e-12, n_bins=1024, offset=0.0),
        speed_of_light=299704644.5,
    )


def lissajous64() -> System:
    """64 × 64 SPAD array (50 µm pixels, f = 6 mm: 30° field) with a Lissajous mirror:
    fast axis 1570 Hz ± 9°, second resonant axis 970.3 Hz ± 11° (frequency ratio near the
    golden ratio: a dense, slowly repeating figure; amplitudes mechanical),
    200 kHz shots, 0.3 ns pulses, 100 ps TDC bins (1024)."""
    return two_axis_system(square_pixel_receiver(64, 64, 50e-6, 6e-3), "resonant",
                           1570.0, math.radians(9.0), 970.3, math.radians(11.0), 200e3)


def raster128x96() -> System:
    """128 × 96 SPAD array (40 µm pixels, f = 6 mm: 46° × 35°) with a raster mirror:
    resonant fast axis 1570 Hz ± 12°, quasi-static slow axis 8 Hz triangle ± 12.5°
    (196 lines a sweep), 400 kHz shots."""
    return two_axis_system(square_pixel_receiver(128, 96, 40e-6, 6e-3), "quasistatic",
                           1570.0, math.radians(12.0), 8.0, math.radians(12.5), 400e3)


#: the one-axis presets (name → function returning the System)
ONE_AXIS_PRESETS = {"burkard2022": burkard2022}
#: the two-axis presets (name → function returning the System)
TWO_AXIS_PRESETS = {"lissajous64": lissajous64, "raster128x96": raster128x96}
#: every preset, one- and two-axis (name → function returning the System): the one
#: registry behind :func:`mems_stereo.model.system.preset`, every ``--system`` option
#: and ``ms.PRESETS``
PRESETS = ONE_AXIS_PRESETS | TWO_AXIS_PRESETS


# --------------------------------------------------------------------------
# what a system argument names


class UnknownPresetError(FormatError, UnknownNameError):
    """A system argument that names neither an existing file nor a preset (a
    ``FormatError``, hence ``ValueError``; also an
    :class:`~mems_stereo.errors.UnknownNameError`, hence ``KeyError``, as a failed
    look-up in :data:`PRESETS` is).  The message's advice line names the nearest
    existing file or preset and lists the presets."""

    def __str__(self) -> str:  # KeyError would print the message's repr
        return str(self.args[0]) if self.args else ""


def presets_advice(name: str) -> str:
    """``did you mean 'X'? presets: ...`` (the nearest preset, where one is near)."""
    near = closest_key(str(name), sorted(PRESETS))
    return ((f"did you mean {near!r}? " if near else "")
            + f"presets: {', '.join(sorted(PRESETS))}")


def looks_like_path(spec: str) -> bool:
    """Whether a system argument is meant as a file: it has a folder part
    (``/``), a suffix (``.json``) or starts with ``~`` or ``.`` — no preset does."""
    s = str(spec)
    seps = [x for x in (os.sep, os.altsep, "/") if x]
    return any(x in s for x in seps) or s.startswith(("~", ".")) or bool(Path(s).suffix)


#: entries of a folder looked at for a "did you mean" file name
_MAX_LISTED = 5000


def nearby_file(spec: str) -> str | None:
    """The existing file in ``spec``'s folder whose name is nearest ``spec``'s
    (one or two typing mistakes), as the user would type it; None when none is near."""
    p = Path(spec)
    folder = p.parent
    try:
        with os.scandir(folder) as it:
            names = [e.name for _i, e in zip(range(_MAX_LISTED), it)
                     if e.is_file() and e.name != p.name]
    except OSError:
        return None
    near = closest_key(p.name, names)
    if near is None:
        return None
    return near if str(folder) in ("", ".") and "/" not in str(spec) else str(folder / near)


def system_source(spec: str | os.PathLike) -> Path | str:
    """What a system argument names: an existing file (its ``Path``), else a preset
    (its name), else :class:`UnknownPresetError` saying which:

    * a path-looking value (:func:`looks_like_path`) that does not exist:
      ``FILE: not found``, advising the nearest existing file of that folder
      (:func:`nearby_file`) or the nearest preset;
    * a bare name that is no preset: ``unknown preset 'NAME'``, advising the
      nearest preset (or the nearest file of the working folder).

    A folder named like a preset does not hide the preset.
    """
    s = os.fspath(spec)
    if not s.strip():
        raise UnknownPresetError("expected a system JSON file or a preset, found an empty "
                                 f"name\npresets: {', '.join(sorted(PRESETS))}")
    p = Path(s)
    if p.exists() and not (s in PRESETS and p.is_dir()):
        return p
    if s in PRESETS:
        return s
    presets = f"presets: {', '.join(sorted(PRESETS))}"
    if looks_like_path(s):
        near, preset = nearby_file(s), closest_key(p.stem, sorted(PRESETS))
        if near is not None:
            advice = f"did you mean {near}?"
        elif preset is not None:
            advice = f"did you mean the preset {preset!r} (named without a folder or suffix)?"
        else:
            where = "" if p.parent.is_dir() else f" (there is no folder {p.parent})"
            advice = f"expected an existing system JSON file{where}, or a preset; {presets}"
        raise UnknownPresetError(f"not found\n{advice}", source=s)
    preset = closest_key(s, sorted(PRESETS))
    near = nearby_file(s) if preset is None else None
    advice = (f"did you mean {preset!r}? " if preset else
              f"did you mean the file {near}? " if near else "")
    raise UnknownPresetError(f"unknown preset {s!r}\n{advice}{presets}, or the path of a "
                             "system JSON file")
