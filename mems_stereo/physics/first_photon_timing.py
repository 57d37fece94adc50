"""First-photon timing of a wide pulse seen by a SPAD behind a TDC that starts late.

A SPAD pixel records only its first photon per shot and the TDC records
nothing before it starts (TDC time τ < 0).  The laser pulse is Gaussian with
FWHM ``pulse_fwhm`` (14.9 ns: σ_p = 6.33 ns, about 1.9 m of path), centred at
the TDC time ``τ0 = L / c + offset`` of the return (``L`` the path length,
``offset`` the TDC offset: ``t_TOF = (N − ½)·bin_width − offset``).

Given ``μ`` expected signal photons in the pixel per shot and a background
rate ``λ`` (Hz, photons that arrive from τ = 0 on and may fire the pixel
first), the density of "the pixel fires first on a signal photon at τ0 + u"
is, on u ≥ a = −τ0::

    h(u) = μ g(u) · exp(−μ (G(u) − G(a)) − λ (u − a))

with g, G the pulse's density and distribution.  Its integral is the
probability of a signal detection, its normalised first moment the bias of
the mean arrival time (early for a strong return: the first of several
photons; late near τ0 = 0: the early part of the pulse is cut off).  The
classes here tabulate these by quadrature; the tests check them against a
Monte-Carlo of photons.
"""

from __future__ import annotations

import math

import numpy as np


def first_photon_moments(a, mu: float, sigma: float, lam: float = 0.0,
                         n_quad: int = 801):
    """Probability, mean and variance of a signal first-photon detection.

    Parameters
    ----------
    a : (N,) float64, s: lower limit −τ0 (the TDC start relative to the pulse
        centre).
    mu : expected signal photons per shot in the pixel (≥ 0).
    sigma : pulse σ, s.
    lam : background rate of the pixel, Hz.
    n_quad : quadrature points over ±8σ.

    Returns
    -------
    p : (N,) probability that the pixel fires first on a signal photon.
    mean : (N,) s, E[u] of that photon's time relative to the pulse centre
        (NaN where p is 0).
    var : (N,) s², its variance.
    """
    from scipy.special import ndtr

    a = np.atleast_1d(np.asarray(a, dtype=np.float64))
    hi = 8.0 * sigma
    lo = np.clip(a, -hi, hi)
    # per row a grid from the cut (or −8σ) to +8σ: the cut is a node, trapezoid is O(du²)
    t = np.linspace(0.0, 1.0, n_quad)
    u = lo[:, None] + (hi - lo)[:, None] * t[None, :]
    du = (hi - lo) / (n_quad - 1)
    z = u / sigma
    g = np.exp(-0.5 * z * z) / (sigma * math.sqrt(2.0 * math.pi))
    Ga = ndtr(a / sigma)[:, None]
    expo = -mu * (ndtr(z) - Ga) - lam * (u - a[:, None])
    h = mu * g * np.exp(np.minimum(expo, 0.0))
    w = np.ones(n_quad)
    w[0] = w[-1] = 0.5
    p = (h @ w) * du
    m1 = ((h * u) @ w) * du
    m2 = ((h * u * u) @ w) * du
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(p > 0, m1 / p, np.nan)
        var = np.where(p > 0, np.maximum(m2 / p - mean * mean, 0.0), np.nan)
    return p, mean, var


class FirstPhotonCurve:
    """Tabulated bias and spread of the first signal photon for one (μ, λ).

    ``mean_time(tau0)`` is E[TDC time of a signal detection] for a return
    centred at TDC time ``tau0`` (s); ``std(tau0)`` its standard deviation
    including the bin quantisation (bin_width/√12).
    """

    def __init__(self, mu: float, sigma: float, lam: float = 0.0, bin_width: float = 0.0,
                 n_grid: int = 321):
        self.mu = float(mu)
        self.sigma = float(sigma)
        self.lam = float(lam)
        self.tau_grid = np.linspace(-4.0 * sigma, 8.0 * sigma, n_grid)
        p, mean, var = first_photon_moments(-self.tau_grid, self.mu, sigma, self.lam)
        self.p = p
        # far below the grid nothing is detected; keep the last finite values
        self.bias = _fill_nan(mean)
        self.var = _fill_nan(var) + bin_width ** 2 / 12.0

    def mean_time(self, tau0) -> np.ndarray:
        t = np.asarray(tau0, dtype=np.float64)
        return t + np.interp(t, self.tau_grid, self.bias)

    def std(self, tau0) -> np.ndarray:
        return np.sqrt(np.interp(np.asarray(tau0, dtype=np.float64), self.tau_grid, self.var))

    def probability(self, tau0) -> np.ndarray:
        return np.interp(np.asarray(tau0, dtype=np.float64), self.tau_grid, self.p)


def _fill_nan(x: np.ndarray) -> np.ndarray:
    x = np.array(x, dtype=np.float64)
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros_like(x)
    idx = np.arange(x.size)
    x[~ok] = np.interp(idx[~ok], idx[ok], x[ok])
    return x


def estimate_signal_rate(fraction: float, tau0: float, sigma: float, lam: float = 0.0,
                         mu_max: float = 50.0) -> float:
    """μ (signal photons per shot) that gives the observed detection fraction.

    Inverts p(μ) = P(signal first photon | return at TDC time ``tau0``) by
    bisection on log μ.  ``fraction`` in [0, 1); returns 0 for 0 and
    ``mu_max`` when the fraction cannot be reached.
    """
    if not fraction > 0:
        return 0.0
    a = np.array([-tau0])
    p_max = first_photon_moments(a, mu_max, sigma, lam)[0][0]
    if fraction >= p_max:
        return mu_max
    lo, hi = math.log(1e-6), math.log(mu_max)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if first_photon_moments(a, math.exp(mid), sigma, lam, n_quad=401)[0][0] < fraction:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def background_rate(noise_fraction: float, window: float) -> float:
    """Background rate (Hz) of a pixel that fires in ``noise_fraction`` of shots
    within a TDC window of ``window`` seconds (Poisson: λ = −ln(1 − f) / T)."""
    f = min(max(float(noise_fraction), 0.0), 1.0 - 1e-12)
    return -math.log1p(-f) / window


class FirstPhotonTable:
    """Bias, variance and detection probability over (τ0, log μ), for one (σ, λ).

    Tabulated by :func:`first_photon_moments` on a grid of τ0 ∈ [−4σ, 10σ]
    (beyond it the values are constant) and log μ ∈ [log 1e−3, log 100];
    looked up by bilinear interpolation (smooth enough for finite-difference
    Jacobians with steps larger than the grid's curvature scale).
    """

    def __init__(self, sigma: float, lam: float = 0.0, bin_width: float = 0.0,
                 n_tau: int = 281, n_mu: int = 81):
        self.sigma = float(sigma)
        self.lam = float(lam)
        self.tau = np.linspace(-4.0 * sigma, 10.0 * sigma, n_tau)
        self.logmu = np.linspace(math.log(1e-3), math.log(100.0), n_mu)
        p = np.empty((n_tau, n_mu))
        bias = np.empty((n_tau, n_mu))
        var = np.empty((n_tau, n_mu))
        for i, lm in enumerate(self.logmu):
            pi, mi, vi = first_photon_moments(-self.tau, math.exp(lm), sigma, lam, n_quad=601)
            p[:, i], bias[:, i], var[:, i] = pi, _fill_nan(mi), _fill_nan(vi)
        self.p, self.bias, self.var = p, bias, var + bin_width ** 2 / 12.0

    def _lookup(self, table, tau0, logmu):
        t = np.asarray(tau0, dtype=np.float64)
        m = np.broadcast_to(np.asarray(logmu, dtype=np.float64), t.shape)
        ft = np.clip((t - self.tau[0]) / (self.tau[1] - self.tau[0]), 0, self.tau.size - 1.000001)
        fm = np.clip((m - self.logmu[0]) / (self.logmu[1] - self.logmu[0]), 0,
                     self.logmu.size - 1.000001)
        it, im = ft.astype(np.int64), fm.astype(np.int64)
        wt, wm = ft - it, fm - im
        return ((1 - wt) * (1 - wm) * table[it, im] + wt * (1 - wm) * table[it + 1, im]
                + (1 - wt) * wm * table[it, im + 1] + wt * wm * table[it + 1, im + 1])

    def mean_time(self, tau0, logmu) -> np.ndarray:
        """E[TDC time] of a signal detection, s, for returns centred at ``tau0``."""
        return np.asarray(tau0, dtype=np.float64) + self._lookup(self.bias, tau0, logmu)

    def std(self, tau0, logmu) -> np.ndarray:
        """Its standard deviation (pulse, first photon, quantisation), s."""
        return np.sqrt(self._lookup(self.var, tau0, logmu))

    def probability(self, tau0, logmu) -> np.ndarray:
        """Probability that the shot gives a signal detection."""
        return self._lookup(self.p, tau0, logmu)
