"""Imperfect hardware for the simulator: the hardware model drawn and applied.

The simulator (:func:`mems_stereo.sim.simulate.simulate`) makes what its *true*
system describes; a true system with the hardware model's members
(``docs/hardware.md``) records as imperfect hardware does.  :class:`Imperfections`
holds the amounts; :meth:`Imperfections.apply` draws the random parts (per-pixel
offsets, the DNL's random part) from a seeded generator and returns the true
system.  :meth:`Imperfections.typical` gives the amounts of issue 30's table
(0.3 % third harmonic, edge delays 300 / 100 ns, a pulse tail, 100 ps pixel
offsets, ±0.1 LSB periodic DNL).  See ``docs/simulator.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mems_stereo.errors import OptionError
from mems_stereo.model.hardware import TDC, Harmonic, MonitorEdges, PulseModel, System
from mems_stereo.model.tdc import code_of_time

__all__ = ["Imperfections", "dnl_code_widths", "imperfect_system", "pixel_delays", "tdc_codes"]


def tdc_codes(t, tdc: TDC) -> np.ndarray:
    """uint16 codes of TDC times ``t`` (s, ≥ 0): ``min(floor(t / bin_width) + 1, n_bins)``
    for equal widths (the simulator's rule, bit for bit), else by the code edges
    (:func:`mems_stereo.model.tdc.code_of_time`)."""
    if tdc.code_widths is None:
        return np.minimum(np.floor(t / tdc.bin_width) + 1, tdc.n_bins).astype(np.uint16)
    return code_of_time(t, tdc).astype(np.uint16)


def pixel_delays(tdc: TDC, pixel) -> np.ndarray:
    """(M,) s: the TDC start delays of flat pixels ``pixel`` (0 without offsets)."""
    if tdc.pixel_offsets is None:
        return np.zeros(np.shape(pixel))
    return np.asarray(tdc.pixel_offsets, dtype=np.float64)[np.asarray(pixel, np.int64)]


def dnl_code_widths(n_bins: int, rng: np.random.Generator, periodic: float = 0.1,
                    period: int = 32, random: float = 0.03) -> np.ndarray:
    """(n_bins,) code widths in LSB: 1 + periodic · sin(2π N / period + ψ) + random · z.

    ψ uniform and z standard normal from ``rng``; widths clipped to ≥ 0.05 LSB and
    scaled to mean 1 (the TDC's range is kept).  A periodic DNL is the usual
    signature of a delay-line TDC's interpolator (``docs/hardware.md``).
    """
    n = np.arange(1, int(n_bins) + 1, dtype=np.float64)
    psi = rng.uniform(0.0, 2 * np.pi)
    w = 1.0 + periodic * np.sin(2 * np.pi * n / period + psi) + random * rng.standard_normal(n.size)
    w = np.maximum(w, 0.05)
    return w / w.mean()


@dataclass(frozen=True)
class Imperfections:
    """Amounts of the five imperfections (0 / empty / None: that one is ideal).

    Attributes
    ----------
    harmonics : tuple
        :class:`~mems_stereo.model.hardware.Harmonic` s (amplitude relative to
        θ_mech,max).
    rising_delay, falling_delay : float
        s, the monitor's edge delays (both 0: none).
    tail_fraction, tail_decay : float
        the ex-gaussian pulse's tail (share, s).
    pixel_offset_sigma : float
        s, σ of the per-pixel TDC offsets (drawn, mean removed).
    dnl_periodic, dnl_period, dnl_random : float, int, float
        the code widths (LSB, codes, LSB; :func:`dnl_code_widths`).
    """

    harmonics: tuple = ()
    rising_delay: float = 0.0
    falling_delay: float = 0.0
    tail_fraction: float = 0.0
    tail_decay: float = 0.0
    pixel_offset_sigma: float = 0.0
    dnl_periodic: float = 0.0
    dnl_period: int = 32
    dnl_random: float = 0.0

    @classmethod
    def typical(cls) -> Imperfections:
        """Typical amounts of a prototype (issue 30): 0.3 % third harmonic, edge
        delays 300 / 100 ns, a 20 % tail of 2 ns, 100 ps pixel offsets, DNL ±0.1 LSB
        periodic (period 32 codes) and 0.03 LSB random."""
        return cls((Harmonic(3, 0.003, 0.0),), 300e-9, 100e-9, 0.2, 2e-9, 100e-12,
                   0.1, 32, 0.03)

    def apply(self, system: System, rng: np.random.Generator) -> System:
        """The true system: ``system`` with these imperfections (random parts from
        ``rng``, in a fixed order: pixel offsets, then the DNL)."""
        if self.tail_fraction and not self.tail_decay > 0:
            raise OptionError("tail_decay: expected a positive decay time with a tail")
        sc, la, tdc = system.scanner, system.laser, system.tdc
        if self.harmonics:
            sc = replace(sc, harmonics=tuple(sorted(self.harmonics, key=lambda h: h.order)))
        if self.rising_delay or self.falling_delay:
            sc = replace(sc, monitor=MonitorEdges(self.rising_delay, self.falling_delay))
        if self.tail_fraction:
            la = replace(la, pulse_shape=PulseModel("ex-gaussian", self.tail_fraction,
                                                    self.tail_decay))
        if self.pixel_offset_sigma > 0:
            n = system.receiver.width * system.receiver.height
            off = rng.normal(0.0, self.pixel_offset_sigma, n)
            tdc = replace(tdc, pixel_offsets=off - off.mean())
        if self.dnl_periodic > 0 or self.dnl_random > 0:
            tdc = replace(tdc, code_widths=dnl_code_widths(
                tdc.n_bins, rng, self.dnl_periodic, self.dnl_period, self.dnl_random))
        return replace(system, scanner=sc, laser=la, tdc=tdc)


def imperfect_system(system: System, seed: int = 0,
                     imperfections: Imperfections | None = None) -> System:
    """``system`` with :meth:`Imperfections.typical` (or the given ones) drawn with
    ``numpy.random.default_rng(seed)``: a seeded true system for :func:`simulate`."""
    imp = Imperfections.typical() if imperfections is None else imperfections
    return imp.apply(system, np.random.default_rng(seed))
