"""Photons: link budget, pulse shape, returned spot, first-photon sampling.

Everything a SPAD pixel sees in one shot is a superposition of independent
Poisson processes (the laser return, shaped by the pulse; ambient light and
dark counts, constant in time).  The pixel records only its *first* photon
after the TDC window opens, so instead of generating every photon the
simulator samples each pixel's first arrival in closed form:

* background + dark counts, rate λ: the first arrival in the window
  [0, T) is a truncated exponential; whether there is one at all is a
  Bernoulli draw with p = 1 − exp(−λT).  Pixel slots that fire are found by
  geometric skipping, so the cost scales with the number of detections;
* the laser return: m ~ Poisson(μ · p_win) photons land inside the window
  (p_win: the share of the pulse inside it); the first of m i.i.d. arrivals
  has CDF 1 − (1 − F)^m, sampled by inversion of the tabulated pulse CDF;
* the detection is the earlier of the two (pile-up emerges by itself).

Times here are TDC times τ = t + offset (s), the TDC window is [0, n_bins · bin_width).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from ..system import Receiver

PLANCK = 6.62607015e-34  # J s
C_VACUUM = 299792458.0  # m/s
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
DENSE_BACKGROUND = 0.5  # above this firing probability, draw every slot instead of skipping


# --------------------------------------------------------------------------
# link budget


@dataclass(frozen=True)
class LinkBudget:
    """Parameters of the optical link (defaults: the paper's system, Table 1).

    peak_power : W, laser peak optical power (80 mW).
    mems_reflectivity : mirror reflectivity at the wavelength (81.25 %).
    focal_length : m, receiver lens (8 mm); f_number : (2) → aperture Ø f/N = 4 mm.
    optics_transmission : lens and window transmission (0.7).
    filter_transmission : 10 nm band-pass at the laser line, including the
        laser diode's spectral width and drift (0.5).
    pde : photon detection efficiency of a SPAD at 659 nm (0.20).
    fill_factor : photosensitive share of a pixel; None → spads_per_pixel
        SPADs of the receiver's ``spad_diameter`` over the pixel area
        (4 · π · (6 µm)² / (40.56 µm · 209.6 µm) = 5.3 %).
    spads_per_pixel : 4 (SPADEye2).
    """

    peak_power: float = 0.080
    mems_reflectivity: float = 0.8125
    focal_length: float = 8e-3
    f_number: float = 2.0
    optics_transmission: float = 0.7
    filter_transmission: float = 0.5
    pde: float = 0.20
    fill_factor: float | None = None
    spads_per_pixel: int = 4

    @property
    def aperture_area(self) -> float:
        """m², entrance pupil area π (f / 2N)²."""
        return math.pi * (self.focal_length / (2.0 * self.f_number)) ** 2

    def pixel_fill_factor(self, receiver: Receiver) -> float:
        if self.fill_factor is not None:
            return float(self.fill_factor)
        spad = self.spads_per_pixel * math.pi * (0.5 * receiver.spad_diameter) ** 2
        return min(1.0, spad / float(np.prod(receiver.pixel_pitch)))

    def receiver_efficiency(self, receiver: Receiver) -> float:
        """Optics × filter × PDE × fill factor (dimensionless)."""
        return (self.optics_transmission * self.filter_transmission * self.pde
                * self.pixel_fill_factor(receiver))


def emitted_photons(budget: LinkBudget, pulse: PulseShape, wavelength: float) -> float:
    """Photons leaving the mirror per pulse: P_peak · ∫shape dt / (h c / λ) · R_MEMS."""
    energy = budget.peak_power * pulse.energy_time
    return energy * wavelength / (PLANCK * C_VACUUM) * budget.mems_reflectivity


def expected_signal_photons(n_emitted: float, reflectivity, cos_emit, cos_view, range_rx,
                            budget: LinkBudget, receiver: Receiver) -> np.ndarray:
    """Mean detected signal photons per shot over the whole returned spot.

    Lambertian target (the whole beam hits it):
    ``μ = N_emit · ρ · cos θ_e / π · A_ap · cos θ_r / R² · η_rx``, where θ_e is
    the angle between the surface normal and the direction to the receiver,
    θ_r the angle of the returning ray to the optical axis, R the distance
    target → projection centre (m) and η_rx :meth:`LinkBudget.receiver_efficiency`.
    Inputs (N,) arrays; returns (N,) float64 (0 where cos θ_e ≤ 0).
    """
    ce = np.clip(np.asarray(cos_emit, float), 0.0, None)
    cv = np.clip(np.asarray(cos_view, float), 0.0, None)
    r = np.asarray(range_rx, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = (n_emitted * np.asarray(reflectivity, float) * ce / math.pi
              * budget.aperture_area * cv / (r * r) * budget.receiver_efficiency(receiver))
    return np.where(np.isfinite(mu), mu, 0.0)


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
            raise ValueError(f"pulse shape: expected times and power of equal shape (m,), m >= 2,"
                             f" found {ts.shape} and {ps.shape}")
        if np.any(np.diff(ts) <= 0) or np.any(ps < 0) or not np.any(ps > 0):
            raise ValueError("pulse shape: expected increasing times and non-negative power "
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


# --------------------------------------------------------------------------
# returned spot on the sensor


@dataclass(frozen=True)
class SpotModel:
    """Size of the imaged laser spot (Gaussian), from beam, defocus and optics.

    beam_diameter : m, beam Ø leaving the mirror (3.3 mm, the mirror aperture).
    beam_divergence : rad, full angle (1 mrad).
    focus_distance : m, where the receiver lens is focused (2.5 m).
    psf_sigma : m on the sensor, the lens's own blur (8 µm).
    radius : pixels considered on each side of the spot centre (2).

    σ² = (D_beam(R_tx) · f / z / 4)² + (c / 4)² + psf², with
    D_beam = beam_diameter + beam_divergence · R_tx and the defocus blur
    circle c = A · f · |1/z − 1/z_focus| (A = aperture Ø, z the depth).
    """

    beam_diameter: float = 3.3e-3
    beam_divergence: float = 1e-3
    focus_distance: float = 2.5
    psf_sigma: float = 8e-6
    radius: int = 2

    def sigma(self, range_tx, depth, budget: LinkBudget) -> np.ndarray:
        """(N,) float64, metres on the sensor."""
        f = budget.focal_length
        z = np.maximum(np.asarray(depth, float), 1e-6)
        d_beam = self.beam_diameter + self.beam_divergence * np.asarray(range_tx, float)
        aperture = f / budget.f_number
        blur = aperture * f * np.abs(1.0 / z - 1.0 / self.focus_distance)
        return np.sqrt((d_beam * f / z / 4.0) ** 2 + (blur / 4.0) ** 2 + self.psf_sigma ** 2)


def spot_fractions(center, sigma_px, image_size, radius: int = 2):
    """Share of a Gaussian spot falling on each nearby pixel.

    center : (N, 2) float64 pixel (column, row) of the spot centre (NaN: off).
    sigma_px : (N, 2) float64 spot σ in pixels (column, row direction).
    image_size : (W, H).
    Returns ``rows (N, nr) int64, cols (N, nc) int64, frac (N, nr, nc) float64``;
    pixels outside the sensor get row/col −1 and fraction 0.
    """
    w, h = int(image_size[0]), int(image_size[1])
    c = np.asarray(center, float)
    s = np.asarray(sigma_px, float)
    ok = np.all(np.isfinite(c), axis=1)
    c = np.where(ok[:, None], c, -1e6)

    def axis(u, su, n, r):
        if n <= 2 * r + 1:
            idx = np.broadcast_to(np.arange(n), (u.size, n)).copy()
        else:
            idx = np.rint(u)[:, None].astype(np.int64) + np.arange(-r, r + 1)
        frac = (ndtr((idx + 0.5 - u[:, None]) / su[:, None])
                - ndtr((idx - 0.5 - u[:, None]) / su[:, None]))
        bad = (idx < 0) | (idx >= n)
        frac[bad] = 0.0
        idx[bad] = -1
        return idx, frac

    cols, fc = axis(c[:, 0], s[:, 0], w, radius)
    rows, fr = axis(c[:, 1], s[:, 1], h, radius)
    frac = fr[:, :, None] * fc[:, None, :]
    frac[~ok] = 0.0
    return rows, cols, frac


# --------------------------------------------------------------------------
# first photons


def first_signal_arrival(mu, delay, pulse: PulseShape, window: float,
                         rng: np.random.Generator):
    """TDC time of the first laser-return photon in each pixel slot.

    mu : (N,) mean signal photons of the slot (whole pulse, before the window).
    delay : (N,) s, TDC time of a photon with zero pulse delay, L/c + offset.
    window : s, n_bins · bin_width.
    Returns ``tau (N,) float64`` (inf where no photon lands in the window)
    and ``m (N,) int64``, the number of signal photons inside the window.

    m ~ Poisson(μ · p_win), p_win = F(window − delay) − F(−delay); the first
    of m has F-quantile F(−delay) + p_win · (1 − (1 − u)^{1/m}).
    """
    mu = np.asarray(mu, float)
    delay = np.asarray(delay, float)
    fa = pulse.cdf_at(-delay)
    fb = pulse.cdf_at(window - delay)
    p = np.clip(fb - fa, 0.0, 1.0)
    m = rng.poisson(mu * p)
    u = rng.random(mu.shape)
    tau = np.full(mu.shape, np.inf)
    hit = m > 0
    if np.any(hit):
        v = -np.expm1(np.log1p(-u[hit]) / m[hit])  # 1 - (1-u)^(1/m)
        s = pulse.ppf(fa[hit] + p[hit] * v)
        tau[hit] = np.clip(delay[hit] + s, 0.0, np.nextafter(window, 0.0))
    return tau, m


def first_photon_cdf(s, mu, pulse: PulseShape) -> np.ndarray:
    """CDF of the first of Poisson(μ) return photons' delay, given at least one.

    ``(1 − exp(−μ F(s))) / (1 − exp(−μ))`` with F the pulse (⊗ jitter) CDF;
    no background and no window.  ``s`` (...) seconds; returns (...) float64.
    """
    return -np.expm1(-mu * pulse.cdf_at(s)) / -math.expm1(-mu)


def first_photon_mean_delay(mu, pulse: PulseShape) -> np.ndarray:
    """Mean delay (s) of the first return photon given ≥ 1, for each μ in ``mu``.

    The pile-up bias of the laser return itself: 0 for μ → 0 (symmetric
    pulse), earlier (negative) as μ grows.  Integrates :func:`first_photon_cdf`
    on the pulse's grid: E[s] = t_max − ∫ G(s) ds over the grid.
    """
    m = np.atleast_1d(np.asarray(mu, dtype=np.float64))
    out = np.empty(m.shape)
    for i, mi in enumerate(m.ravel()):
        g = pulse.cdf if mi <= 1e-9 else -np.expm1(-mi * pulse.cdf) / -math.expm1(-mi)
        out.ravel()[i] = pulse.t[-1] - np.trapezoid(g, pulse.t)
    return out.reshape(np.shape(mu))


def background_first_arrivals(rate_hz: float, n_slots: int, window: float,
                              rng: np.random.Generator):
    """First background/dark arrival in each of ``n_slots`` pixel slots.

    Constant rate λ = ``rate_hz``: a slot fires within [0, window) with
    p = 1 − exp(−λ·window) (Bernoulli, found by geometric skipping), and its
    first arrival is exponential truncated to the window.  When most slots fire
    (p > 0.5) each slot instead gets one float32 uniform u: it fires when
    u < p, at the exponential quantile −ln(1 − u)/λ (same law).
    Returns ``index (M,) int64`` (slots that fire, increasing) and ``tau (M,)
    float64`` s.
    """
    lam = float(rate_hz)
    if lam <= 0 or n_slots <= 0:
        return np.zeros(0, np.int64), np.zeros(0)
    p = -math.expm1(-lam * window)
    if p > DENSE_BACKGROUND:
        # most slots fire: one uniform per slot, u < p fires at the exponential quantile u
        u = rng.random(n_slots, dtype=np.float32)
        idx = np.flatnonzero(u < p)
        tau = np.log1p(-u[idx])
        tau *= np.float32(-1.0 / lam)  # float32: 1e-7 relative, far below a TDC bin
        return idx, np.minimum(tau, np.float32(window * (1 - 1e-6)))
    else:
        chunks = []
        pos = -1
        while True:
            n_est = int(n_slots * p + 6.0 * math.sqrt(n_slots * p) + 16)
            g = rng.geometric(p, size=n_est)
            c = pos + np.cumsum(g)
            chunks.append(c[c < n_slots])
            if c[-1] >= n_slots:
                break
            pos = int(c[-1])
        idx = np.concatenate(chunks).astype(np.int64)
    u = rng.random(idx.size)
    tau = -np.log1p(-u * p) / lam
    tau = np.minimum(tau, np.nextafter(window, 0.0))
    return idx, tau
