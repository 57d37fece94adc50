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

import numpy as np

from mems_stereo.physics.pulse import PulseShape

DENSE_BACKGROUND = 0.5  # above this firing probability, draw every slot instead of skipping


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
