"""The laser pulse: FWHM ↔ σ, and the tabulated pulse shape (⊗ SPAD jitter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erfc, erfcx, ndtr

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


# --------------------------------------------------------------------------
# the laser's pulse model (docs/hardware.md)


def emg_pdf(t, sigma: float, tau: float) -> np.ndarray:
    """Density of N(0, σ) + Exp(mean τ) (exponentially modified Gaussian), 1/s.

    ``f(t) = exp(−t²/2σ²) · erfcx(z) / 2τ`` with z = (σ/τ − t/σ)/√2 (scaled form,
    no overflow), and ``exp(σ²/2τ² − t/τ) · erfc(z) / 2τ`` where z < 0.
    """
    t = np.asarray(t, dtype=np.float64)
    z = (sigma / tau - t / sigma) / math.sqrt(2.0)
    with np.errstate(over="ignore", under="ignore"):
        pos = np.exp(-0.5 * (t / sigma) ** 2) * erfcx(np.maximum(z, 0.0))
        neg = np.exp(np.minimum(0.5 * (sigma / tau) ** 2 - t / tau, 700.0)) * erfc(z)
    return np.where(z >= 0, pos, neg) / (2.0 * tau)


def emg_cdf(t, sigma: float, tau: float) -> np.ndarray:
    """CDF of N(0, σ) + Exp(mean τ): ``Φ(t/σ) − τ·f(t)`` (:func:`emg_pdf`)."""
    return ndtr(np.asarray(t, dtype=np.float64) / sigma) - tau * emg_pdf(t, sigma, tau)


def ex_gaussian_shape(sigma_core: float, tail_fraction: float, tail_decay: float,
                      jitter: float = 0.0, n: int = 4001) -> PulseShape:
    """The ex-gaussian pulse (1 − w)·N(0, σ) + w·EMG(σ, τ), ⊗ Gaussian jitter.

    ``sigma_core`` σ of the Gaussian core (s), w = ``tail_fraction``, τ =
    ``tail_decay`` (s); EMG is the Gaussian convolved with an exponential of mean
    τ (Grushka 1972; :func:`emg_pdf`).  The jitter widens the core:
    σ_j = √(σ² + jitter²) in both parts.  ``energy_time`` is ∫P dt / P_peak of the
    pulse without jitter.  Delay 0 is the core's peak; the mean delay is w·τ.
    """
    sj = max(math.hypot(sigma_core, jitter), 1e-13)
    w, tau = float(tail_fraction), float(tail_decay)
    tail = w > 0 and tau > 0
    t = np.linspace(-8 * sj, 8 * sj + (12 * tau if tail else 0.0), n)

    def mix(s):
        c = (1 - w) * ndtr(t / s)
        d = (1 - w) * np.exp(-0.5 * (t / s) ** 2) / (s * math.sqrt(2 * math.pi))
        if tail:
            c = c + w * emg_cdf(t, s, tau)
            d = d + w * emg_pdf(t, s, tau)
        return c, d

    cdf, _ = mix(sj)
    energy = float(1.0 / mix(sigma_core)[1].max()) if sigma_core > 0 else 0.0
    return PulseShape(t, _strict(cdf), energy)


def pulse_shape_of(laser, jitter: float = 0.0) -> PulseShape:
    """The :class:`PulseShape` of a :class:`~mems_stereo.model.hardware.Laser` ⊗ jitter σ
    (s): its ``pulse_shape`` model, or the Gaussian of ``pulse_fwhm`` (exactly
    :meth:`PulseShape.gaussian`) without one."""
    p = laser.pulse_shape
    if p is None:
        return PulseShape.gaussian(laser.pulse_fwhm, jitter)
    if p.model == "table":
        return PulseShape.from_samples(p.times, p.power, jitter)
    return ex_gaussian_shape(laser.pulse_fwhm * FWHM_TO_SIGMA, p.tail_fraction, p.tail_decay,
                             jitter)


def pulse_sigma_of(laser) -> float:
    """Standard deviation of the pulse's delay, s, without jitter: ``pulse_fwhm`` /
    2.3548 for the Gaussian (bit for bit as :data:`FWHM_PER_SIGMA` gives it);
    √(σ² + w(2 − w)τ²) for the ex-gaussian; the table's second central moment."""
    p = laser.pulse_shape
    if p is None:
        return laser.pulse_fwhm / FWHM_PER_SIGMA
    if p.model == "table":
        t = np.asarray(p.times, dtype=np.float64)
        w = np.asarray(p.power, dtype=np.float64)
        m0 = np.trapezoid(w, t)
        m1 = np.trapezoid(t * w, t) / m0
        return float(math.sqrt(max(np.trapezoid((t - m1) ** 2 * w, t) / m0, 0.0)))
    s = laser.pulse_fwhm * FWHM_TO_SIGMA
    w, tau = p.tail_fraction, p.tail_decay
    return math.sqrt(s * s + w * (2.0 - w) * tau * tau)


def effective_fwhm(laser) -> float:
    """Width (s) of the matched box filters: ``pulse_fwhm`` for the Gaussian; the
    FWHM of a Gaussian with the pulse's σ (:func:`pulse_sigma_of`) otherwise."""
    if laser.pulse_shape is None:
        return laser.pulse_fwhm
    return FWHM_PER_SIGMA * pulse_sigma_of(laser)
