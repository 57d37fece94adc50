"""Named systems: the paper's one-axis system and two two-axis examples.

Each preset is a function returning a :class:`~mems_stereo.model.hardware.System`;
:data:`PRESETS` (one-axis) and :data:`TWO_AXIS_PRESETS` map their names to them.
Resolving a name, a path or an instance to a system is
:func:`mems_stereo.model.system.resolve_system`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from mems_stereo.model.hardware import TDC, Laser, Receiver, Scanner, System
from mems_stereo.model.scanner2d import Axis2, fast_axis


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


TWO_AXIS_PRESETS = {"lissajous64": lissajous64, "raster128x96": raster128x96}
