"""The laser pulse: FWHM ↔ σ, and the tabulated pulse shape (⊗ SPAD jitter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from mems_stereo.errors import FormatError

#: FWHM / σ of a Gaussian, 2·sqrt(2 ln 2)
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


# --------------------------------------------------------------------------
# pulse shape


@dataclass(frozen=True)
class PulseShape:
    """A laser pulse convolved with the timing jitter, tabulated.

    t : (n,) float64 s, increasing grid; cdf : (n,) float64 the CDF of a
    return photon's delay (pulse ⊗ Gaussian jitter) on that grid;
    energy_time : s, ∫ P(t) dt / P_peak (pulse energy = P_peak · energy_time).
    Delay 0 is t = 0 of the given shape (for the Gaussian: its peak).
    """

    t: np.ndarray
    cdf: np.ndarray
    energy_time: float

    @classmethod
    def gaussian(cls, fwhm: float, jitter: float = 0.0, n: int = 4001) -> PulseShape:
        """Gaussian pulse of ``fwhm`` (s) and Gaussian timing jitter σ = ``jitter`` (s)."""
        sp = fwhm * FWHM_TO_SIGMA
        s = max(math.hypot(sp, jitter), 1e-13)
        t = np.linspace(-8 * s, 8 * s, n)
        energy = sp * math.sqrt(2 * math.pi) if sp > 0 else 0.0
        return cls(t, _strict(ndtr(t / s)), energy)

    @classmethod
    def from_samples(cls, times, power, jitter: float = 0.0, n: int = 8001) -> PulseShape:
        """Any sampled pulse: ``times`` (m,) s increasing, ``power`` (m,) ≥ 0 (any scale).

        The shape is linearly interpolated, convolved with the Gaussian jitter
        and tabulated on ``n`` points.
        """
        ts = np.asarray(times, dtype=np.float64)
        ps = np.asarray(power, dtype=np.float64)
        if ts.ndim != 1 or ts.shape != ps.shape or ts.size < 2:
            raise FormatError(f"pulse shape: expected times and power of equal shape (m,), m >= 2,"
                             f" found {ts.shape} and {ps.shape}")
        if np.any(np.diff(ts) <= 0) or np.any(ps < 0) or not np.any(ps > 0):
            raise FormatError("pulse shape: expected increasing times and non-negative power "
                             "with a positive peak")
        pad = 6.0 * jitter
        t = np.linspace(ts[0] - pad, ts[-1] + pad, n)
        dens = np.interp(t, ts, ps, left=0.0, right=0.0)
        dt = t[1] - t[0]
        if jitter > 0:
            k = np.arange(-math.ceil(pad / dt), math.ceil(pad / dt) + 1) * dt
            ker = np.exp(-0.5 * (k / jitter) ** 2)
            dens = np.convolve(dens, ker / ker.sum(), mode="same")
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * dt)])
        energy = float(np.trapezoid(ps, ts) / ps.max())
        return cls(t, _strict(cdf / cdf[-1]), energy)

    def cdf_at(self, s) -> np.ndarray:
        """F(s), the probability that a photon's delay is ≤ s (s in seconds)."""
        return np.interp(s, self.t, self.cdf, left=0.0, right=1.0)

    def ppf(self, u) -> np.ndarray:
        """Inverse CDF: delay (s) of quantile ``u`` in [0, 1]."""
        return np.interp(u, self.cdf, self.t)


def _strict(cdf: np.ndarray) -> np.ndarray:
    """Make a CDF strictly increasing (tiny ramp) so its inverse is single-valued."""
    ramp = np.linspace(0.0, 1e-12, cdf.size)
    c = (cdf + ramp - ramp[0]) / (cdf[-1] + ramp[-1])
    c[0], c[-1] = 0.0, 1.0
    return c

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def pulse_sigma(pulse_fwhm: float, jitter: float = 0.0) -> float:
    """σ of the Gaussian arrival spread, s: pulse (FWHM → σ) ⊕ SPAD jitter σ."""
    return math.hypot(pulse_fwhm * FWHM_TO_SIGMA, jitter)
