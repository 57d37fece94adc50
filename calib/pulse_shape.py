"""The pulse shape from wall returns at low pile-up: an ex-Gaussian tail against the Gaussian.

At low pile-up (a fraction of a signal photon per shot and pixel) a SPAD's
first photon is the return's photon and its time, less the predicted
return time (a fitted wall's τ_k), samples the instrument response: the
laser pulse ⊗ SPAD and TDC jitter ⊗ the TDC's quantisation.  The model is
that of :class:`mems_stereo.model.hardware.PulseModel` (``"ex-gaussian"``):

``f(x) = (1 − w)·N(x; μ, s) + w·EMG(x; μ, s, τ)``,

the Gaussian core of σ ``s`` (quantisation adds ``q²/12``: the core σ reported
is ``sqrt(s² − q²/12)``), a share ``w`` of it delayed by an exponential of
decay ``τ`` (the exponentially modified Gaussian, Grushka 1972, Anal. Chem.
44, 1733; ``scipy.stats.exponnorm``), plus a uniform background share ``b``
over the analysed window.  μ is the core's peak (delay 0 of the pulse model);
the pulse's **mean delay** is ``w·τ``, what processing subtracts.

:func:`fit_pulse_shape` fits (μ, s, w, τ, b) by maximum likelihood and the
Gaussian (w = 0) alike; σ from the inverse observed information (numerical
Hessian); the tail counts as significant when twice the log-likelihood gain
exceeds :data:`TAIL_CHI2` (χ²₂ at 10⁻³: conservative for the boundary w = 0
where τ is not defined).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, special, stats

from mems_stereo.errors import ShapeError
from mems_stereo.model.hardware import PulseModel

#: 2·Δlog L above which the tail is significant (χ² with 2 dof at 1e-3)
TAIL_CHI2 = float(stats.chi2.isf(1e-3, 2))
#: fewest residuals a fit is attempted with
MIN_SAMPLES = 200
#: names of the fitted parameters, in :attr:`PulseFit.cov` order
PARAMS = ("shift", "sigma", "tail_fraction", "tail_decay", "background")


@dataclass(frozen=True)
class PulseFit:
    """The fitted pulse shape (s; shares dimensionless).

    shift : s, the core's peak relative to the predicted return time.
    sigma : s, the Gaussian core's σ (quantisation removed).
    tail_fraction, tail_decay : w and τ (s) of the ex-Gaussian tail.
    mean_delay : s, ``w·τ`` (mean of the pulse relative to its core's peak).
    background : share of uniform background in the window.
    std : dict name → σ (names of :data:`PARAMS` and ``mean_delay``).
    cov : (5, 5) covariance of :data:`PARAMS` (SI).
    loglik, loglik_gaussian : maximum log-likelihoods with and without the tail.
    gaussian_sigma : s, the core σ the Gaussian-only fit finds.
    n : residuals used.  quantum : s, the TDC bin width folded into the core.
    mean_delay_interval : (lo, hi) s, the mean delay's 68 % profile-likelihood
        interval (:func:`fit_return_shape`; None for plain residuals).
    signal_scale : κ, the fitted factor on the cells' expected signal (1: plain).
    With :class:`ReturnSamples` the fifth parameter of ``cov`` is κ, not the
    background share (``background`` then is the share of the used detections
    the background explains).
    """

    shift: float
    sigma: float
    tail_fraction: float
    tail_decay: float
    mean_delay: float
    background: float
    std: dict
    cov: np.ndarray
    loglik: float
    loglik_gaussian: float
    gaussian_sigma: float
    n: int
    quantum: float
    mean_delay_interval: tuple | None = None
    signal_scale: float = 1.0

    @property
    def tail_significant(self) -> bool:
        """The tail improves the fit beyond chance (2·Δlog L > :data:`TAIL_CHI2`)."""
        return 2.0 * (self.loglik - self.loglik_gaussian) > TAIL_CHI2

    def pdf(self, x, gaussian: bool = False) -> np.ndarray:
        """Density of the signal part (no background) at delays ``x`` (s) relative to
        the predicted time; ``gaussian``: the Gaussian-only fit's (same shift)."""
        s = math.hypot(self.sigma, self.quantum / math.sqrt(12.0))
        if gaussian:
            sg = math.hypot(self.gaussian_sigma, self.quantum / math.sqrt(12.0))
            return stats.norm.pdf(np.asarray(x), self.shift, sg)
        return _signal_pdf(np.asarray(x, dtype=np.float64), self.shift, s,
                           self.tail_fraction, self.tail_decay)

    def to_pulse_model(self) -> PulseModel:
        """The ex-Gaussian :class:`~mems_stereo.model.hardware.PulseModel` with σ."""
        return PulseModel("ex-gaussian", self.tail_fraction, self.tail_decay,
                          self.std["tail_fraction"], self.std["tail_decay"])

    def summary(self) -> str:
        """One line: core σ, tail share and decay, mean delay, each ± σ, and the verdict."""
        sd = self.std
        verdict = "tail significant" if self.tail_significant else "Gaussian suffices"
        return (f"pulse: core σ {self.sigma * 1e9:.3f} ± {sd['sigma'] * 1e9:.3f} ns, tail "
                f"{self.tail_fraction * 100:.1f} ± {sd['tail_fraction'] * 100:.1f} % with decay "
                f"{self.tail_decay * 1e9:.2f} ± {sd['tail_decay'] * 1e9:.2f} ns, mean delay "
                f"{self.mean_delay * 1e12:.0f} ± {sd['mean_delay'] * 1e12:.0f} ps "
                f"(2·Δlog L {2 * (self.loglik - self.loglik_gaussian):.1f}: {verdict}; "
                f"{self.n} returns{self._need()})")

    def returns_for(self, sigma: float = 50e-12) -> float:
        """Low-pile-up returns the mean delay needs for σ = ``sigma`` (s) at this
        shape: ``n·(σ_now/σ)²`` (inf when the fit gives no finite σ)."""
        sd = self.std.get("mean_delay", math.inf)
        return self.n * (sd / sigma) ** 2 if math.isfinite(sd) and sd > 0 else math.inf

    def _need(self) -> str:
        n = self.returns_for()
        return f"; σ 50 ps needs ≈ {n:.1e} such returns" if math.isfinite(n) and n > self.n else ""


def _emg(x, mu, s, tau):
    """EMG density and CDF at x (erfcx form: no overflow for small τ/σ)."""
    z = (x - mu) / s
    u = s / tau - z
    r = s / tau
    with np.errstate(over="ignore", invalid="ignore"):
        # u ≥ 0: e^{−z²/2}·erfcx(u/√2); u < 0: e^{r²/2 − r·z}·erfc(u/√2) (both finite)
        pos = np.exp(-0.5 * z * z) * special.erfcx(np.maximum(u, 0.0) / math.sqrt(2.0))
        neg = np.exp(0.5 * r * r - r * np.maximum(z, r)) * special.erfc(np.minimum(u, 0.0)
                                                                        / math.sqrt(2.0))
    pdf = np.where(u >= 0, pos, neg) / (2.0 * tau)
    return pdf, special.ndtr(z) - tau * pdf


def _signal_pdf(x, mu, s, w, tau):
    core = np.exp(-0.5 * ((x - mu) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))
    if w <= 0.0 or tau <= 0.0:
        return core
    return (1.0 - w) * core + w * _emg(x, mu, s, tau)[0]


def _signal_cdf(x, mu, s, w, tau):
    core = special.ndtr((x - mu) / s)
    if w <= 0.0 or tau <= 0.0:
        return core
    return (1.0 - w) * core + w * _emg(x, mu, s, tau)[1]


def _negloglik(p, hist):
    """−log L (multinomial, binned) of natural parameters p = (μ, s, w, τ, b);
    ``hist`` = (edges (B+1,), counts (B,)) over the window."""
    edges, n = hist
    mu, s, w, tau, b = p
    if s <= 0 or not 0 <= w < 1 or tau < 0 or not 0 <= b < 1:
        return np.inf
    F = _signal_cdf(edges, mu, s, w, tau)
    mass = F[-1] - F[0]
    if not mass > 0:
        return np.inf
    prob = (1.0 - b) * np.diff(F) / mass + b * np.diff(edges) / (edges[-1] - edges[0])
    return -float(n @ np.log(np.maximum(prob, 1e-300)))


def _to_natural(z, scale, tail: bool):
    mu, ls, lw, lt, lb = z
    w, tau = (1 / (1 + math.exp(-lw)), math.exp(lt) * scale) if tail else (0.0, 0.0)
    return np.array([mu * scale, math.exp(ls) * scale, w, tau, 1 / (1 + math.exp(-lb))])


def _fit(hist, scale, starts, tail: bool):
    """Best of several starts (unconstrained parameters z); returns natural p, −log L."""
    width = (hist[0][-1] - hist[0][0]) / scale
    bounds = [(None, None), (math.log(0.05), math.log(width)), (-12.0, 4.0),
              (math.log(0.02), math.log(width)), (-14.0, 2.0)]
    best = None
    for z0 in starts:
        r = optimize.minimize(lambda z: _negloglik(_to_natural(z, scale, tail), hist), z0,
                              method="L-BFGS-B", bounds=bounds)
        if best is None or r.fun < best[1]:
            best = (r.x, r.fun)
    return _to_natural(best[0], scale, tail), best[1]


def _hessian(f, p, steps):
    """Central-difference Hessian of f at p with per-parameter steps."""
    n = p.size
    H = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            e_i = np.zeros(n)
            e_j = np.zeros(n)
            e_i[i], e_j[j] = steps[i], steps[j]
            v = (f(p + e_i + e_j) - f(p + e_i - e_j) - f(p - e_i + e_j) + f(p - e_i - e_j))
            H[i, j] = H[j, i] = v / (4.0 * steps[i] * steps[j])
    return H


def fit_pulse_shape(residuals, *, window=None, quantum: float = 0.0) -> PulseFit:
    """Fit the ex-Gaussian pulse (and the Gaussian) to return-time residuals.

    Parameters
    ----------
    residuals : (N,) float64 s, measured first-photon time minus the predicted
        return time, of signal cells at low pile-up (see module docstring); or
        :class:`ReturnSamples` (:func:`wall_return_residuals`), then fitted by the
        first-photon law (:func:`fit_return_shape`; ``window`` is theirs).
    window : (lo, hi) s analysed (default the residuals' range); residuals
        outside are dropped; background is uniform over it.
    quantum : s, the TDC bin width (its uniform spread is folded into the core).

    Returns
    -------
    PulseFit.  Raises :class:`~mems_stereo.errors.ShapeError` with fewer than
    :data:`MIN_SAMPLES` residuals.
    """
    if isinstance(residuals, ReturnSamples):
        return fit_return_shape(residuals, quantum)
    x = np.asarray(residuals, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    lo, hi = (float(x.min()), float(x.max())) if window is None else map(float, window)
    x = x[(x >= lo) & (x <= hi)]
    if x.size < MIN_SAMPLES:
        raise ShapeError(f"pulse shape: expected at least {MIN_SAMPLES} residuals in the "
                         f"window, found {x.size}")
    q = np.percentile(x, [16, 50, 84])
    scale = max(0.5 * (q[2] - q[0]), 1e-13)
    nb = int(min(4000, max(50, 20 * (hi - lo) / scale)))
    edges = np.linspace(lo, hi, nb + 1)
    hist = (edges, np.histogram(x, edges)[0].astype(np.float64))
    pg, nllg = _fit(hist, scale, [np.array([q[1] / scale, 0.0, 0.0, 0.0, -4.0])], tail=False)
    zg = [pg[0] / scale, math.log(pg[1] / scale), 0.0, 0.0, math.log(pg[4] / (1 - pg[4]) + 1e-12)]
    starts = [np.array([zg[0] - 0.3 * t0, zg[1] - 0.2, -1.5, math.log(t0), zg[4]])
              for t0 in (0.3, 1.0, 3.0)]
    p, nll = _fit(hist, scale, starts, tail=True)
    steps = np.array([1e-3 * p[1], 1e-3 * p[1], 1e-3 * max(p[2], 1e-3),
                      1e-3 * max(p[3], 1e-2 * p[1]), 1e-3 * max(p[4], 1e-4)])
    steps[2] = min(steps[2], 0.5 * p[2]) if p[2] > 0 else steps[2]
    H = _hessian(lambda pp: _negloglik(pp, hist), p, steps)
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.full((5, 5), np.inf)
    var = np.diag(cov)
    sd = {n: float(math.sqrt(v)) if v >= 0 else math.inf for n, v in zip(PARAMS, var)}
    grad = np.array([0.0, 0.0, p[3], p[2], 0.0])  # ∂(w·τ)
    vm = float(grad @ cov @ grad)
    sd["mean_delay"] = math.sqrt(vm) if vm >= 0 else math.inf
    qv = quantum * quantum / 12.0
    core = math.sqrt(max(p[1] ** 2 - qv, 0.0))
    sd["sigma"] = sd["sigma"] * p[1] / core if core > 0 else math.inf
    gcore = math.sqrt(max(pg[1] ** 2 - qv, 0.0))
    return PulseFit(float(p[0]), core, float(p[2]), float(p[3]), float(p[2] * p[3]),
                    float(p[4]), sd, cov, -float(nll), -float(nllg), gcore, int(x.size),
                    float(quantum))


@dataclass(frozen=True)
class ReturnSamples:
    """Wall returns for the first-photon shape fit (:func:`fit_return_shape`), one
    entry per cell that fired inside its window.

    residual : (N,) s, the detection's time less the predicted return time.
    signal : (N,) expected signal photons of the cell (the calibration's m).
    background : (N,) Hz, the cell's background rate.
    upper : (N,) s, the window's upper end for that cell (residual scale: codes
        after the cells' ``t_max`` are not recorded).
    lower : s, the window's lower end (the pixel is armed there).
    core : s or None, the Gaussian core's σ held fixed (the system's pulse σ with
        jitter: the ex-gaussian model's core is ``pulse_fwhm``), None: fitted.
    """

    residual: np.ndarray
    signal: np.ndarray
    background: np.ndarray
    upper: np.ndarray
    lower: float
    core: float | None = None


#: grid steps per pulse scale (the residuals' half 16–84 % range) of the first-photon
#: fit's table of the pulse (fixed in time; at most :data:`FP_GRID` points)
FP_STEPS = 40
FP_GRID = 4001


class _Tabulated:
    """A :class:`ReturnSamples` on the fixed time grid of the first-photon fit:
    interpolation indices and weights of the residuals and the windows' ends."""

    def __init__(self, data: ReturnSamples, scale: float):
        self.data = data
        top = float(np.max(data.upper))
        n = int(min(FP_GRID, max(200, FP_STEPS * (top - data.lower) / scale)))
        self.grid = np.linspace(data.lower, top, n)
        h = self.grid[1] - self.grid[0]
        self.at = [self._weights(v, h) for v in (data.residual, data.upper)]
        self.bx = data.background * (data.residual - data.lower)
        self.bh = data.background * (data.upper - data.lower)

    def _weights(self, v, h):
        u = np.clip((v - self.grid[0]) / h, 0.0, self.grid.size - 1.000001)
        i = np.floor(u).astype(np.int64)
        return i, u - i

    def lookup(self, table, which: int):
        i, a = self.at[which]
        return table[i] * (1.0 - a) + table[i + 1] * a


def _fp_negloglik(p, tab: _Tabulated) -> float:
    """−log L of the first-photon law (:func:`fit_return_shape`) at p = (μ, s, w, τ, κ);
    the pulse's density and CDF are tabulated on the fixed grid of ``tab`` (the
    likelihood stays smooth in p) and interpolated (error ~1e-6 for steps ≪ σ)."""
    mu, s, w, tau, kap = p
    if s <= 0 or not 0 <= w < 1 or tau < 0 or kap <= 0:
        return np.inf
    d, grid = tab.data, tab.grid
    m, b = kap * d.signal, d.background
    fg = np.exp(-0.5 * ((grid - mu) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))
    Fg = special.ndtr((grid - mu) / s)
    if w > 0 and tau > 0:
        ep, ec = _emg(grid, mu, s, tau)
        Fg, fg = (1.0 - w) * Fg + w * ec, (1.0 - w) * fg + w * ep
    Fg = Fg - Fg[0]
    F, FH, f = tab.lookup(Fg, 0), tab.lookup(Fg, 1), tab.lookup(fg, 0)
    with np.errstate(divide="ignore"):
        ll = (np.log(np.maximum(m * f + b, 1e-300)) - m * F - tab.bx
              - np.log(np.maximum(-np.expm1(-m * FH - tab.bh), 1e-300)))
    v = -float(np.sum(ll))
    return v if np.isfinite(v) else np.inf


def _fp_fit(data: ReturnSamples, scale: float, starts, mode):
    """Best of several starts of the first-photon fit; ``mode`` "gauss" (w = 0),
    "tail", or a fixed mean delay d (s, w = d/τ).  Returns natural p, −log L, z."""
    width = (float(np.max(data.upper)) - data.lower) / scale
    tab = _Tabulated(data, scale)

    def nat(z):
        mu, s, kap = z[0] * scale, math.exp(z[1]) * scale, math.exp(z[-1])
        if mode == "gauss":
            return np.array([mu, s, 0.0, 0.0, kap])
        if mode == "tail":
            return np.array([mu, s, 1 / (1 + math.exp(-z[2])), math.exp(z[3]) * scale, kap])
        tau = mode + math.exp(z[2]) * scale
        return np.array([mu, s, mode / tau, tau, kap])

    ls = None if data.core is None else math.log(data.core / scale)
    b = [(None, None), (math.log(0.05), math.log(width)) if ls is None else (ls, ls)]
    b += {"gauss": [], "tail": [(-12.0, 4.0), (math.log(0.02), math.log(width))]}.get(
        mode, [(-12.0, math.log(width))])
    b += [(math.log(0.2), math.log(5.0))]
    best = None
    for z0 in starts:
        z0 = np.array(z0, dtype=np.float64)
        z0[1] = z0[1] if ls is None else ls
        r = optimize.minimize(lambda z: _fp_negloglik(nat(z), tab), z0, method="L-BFGS-B",
                              bounds=b)
        if best is None or r.fun < best[1]:
            best = (nat(r.x), float(r.fun), r.x)
    return best


def _profile_interval(data, scale, p_hat, nll_hat, guess):
    """The mean delay's 68 % profile-likelihood interval (2·Δlog L = 1), s."""
    d_hat = float(p_hat[2] * p_hat[3])

    def excess(d):
        if d <= 0:
            return _fp_fit(data, scale, [np.array([p_hat[0] / scale, math.log(p_hat[1] / scale),
                                                   math.log(p_hat[4])])], "gauss")[1] - nll_hat
        t0 = max(p_hat[3] - d, 0.05 * scale) / scale
        z0 = np.array([(p_hat[0] + d_hat - d) / scale, math.log(p_hat[1] / scale),
                       math.log(t0), math.log(p_hat[4])])
        return _fp_fit(data, scale, [z0], d)[1] - nll_hat

    ends = []
    guess = min(guess, scale) if math.isfinite(guess) else 0.1 * scale
    for sign in (-1.0, 1.0):
        step, inner, e_in, outer = max(guess, 0.02 * scale), d_hat, 0.0, None
        for _ in range(8):  # bracket the crossing, then interpolate in √excess
            d = d_hat + sign * step
            if sign < 0 and d <= 0:
                d = 0.0
            e = excess(d)
            if not e < 0.5:  # beyond the interval (or outside the model)
                outer = (d, e)
                break
            inner, e_in = d, max(e, 0.0)
            if d == 0.0:
                break
            step *= 2.0
        if outer is None:
            ends.append(inner)
            continue
        r_in, r_out = math.sqrt(e_in), math.sqrt(outer[1]) if math.isfinite(outer[1]) else 0.0
        frac = (math.sqrt(0.5) - r_in) / (r_out - r_in) if r_out > r_in else 1.0
        ends.append(inner + (outer[0] - inner) * min(max(frac, 0.0), 1.0))
    return min(ends), max(ends)


def fit_return_shape(data: ReturnSamples, quantum: float = 0.0) -> PulseFit:
    """The ex-Gaussian pulse from wall returns by the first-photon law.

    Per cell, given its expected signal m (scaled by a fitted κ: the calibration's
    amplitudes assume its pulse model) and background rate β, the first detection
    in the window [lo, hi] has density ``(κm·f(x) + β)·exp(−κm·(F(x) − F(lo)) −
    β(x − lo)) / (1 − exp(−κm·(F(hi) − F(lo)) − β(hi − lo)))`` (f, F the pulse's
    density and CDF around the shift μ): pile-up (the first of several photons is
    early), background before the return and each cell's window are exact, not
    approximated.  With ``data.core`` the core's σ is held (the model the fit
    writes, :meth:`PulseFit.to_pulse_model`, takes its core from ``pulse_fwhm``).
    σ of the mean delay ``w·τ`` from its profile likelihood
    (``std["mean_delay"]`` half the 68 % interval, :attr:`PulseFit.mean_delay_interval`):
    the tail of a pulse much wider than its decay is close to a shift, and the
    local curvature understates how far the data allow it to go.
    """
    x = np.asarray(data.residual, dtype=np.float64)
    if x.size < MIN_SAMPLES:
        raise ShapeError(f"pulse shape: expected at least {MIN_SAMPLES} residuals in the "
                         f"window, found {x.size}")
    q = np.percentile(x, [16, 50, 84])
    scale = max(0.5 * (q[2] - q[0]), 1e-13)
    pg, nllg, zg = _fp_fit(data, scale, [np.array([q[1] / scale, 0.0, 0.0])], "gauss")
    starts = [np.array([zg[0] - 0.3 * t0, zg[1] - 0.2, -1.5, math.log(t0), zg[2]])
              for t0 in (0.3, 1.0, 3.0)]
    p, nll, _ = _fp_fit(data, scale, starts, "tail")
    if nllg < nll:  # the Gaussian is the tail's limit w → 0: the optimiser fell short
        p, nll = np.array([pg[0], pg[1], 0.0, p[3], pg[4]]), nllg
    p5 = np.array([p[0], p[1], p[2], p[3], p[4]])
    steps = np.array([1e-3 * p[1], 1e-3 * p[1], 1e-3 * max(p[2], 1e-3),
                      1e-3 * max(p[3], 1e-2 * p[1]), 1e-3 * p[4]])
    steps[2] = min(steps[2], 0.5 * p[2]) if p[2] > 0 else steps[2]
    tab = _Tabulated(data, scale)
    free = np.array([0, 2, 3, 4] if data.core is not None else [0, 1, 2, 3, 4])

    def nll_free(v):
        pp = p5.copy()
        pp[free] = v
        return _fp_negloglik(pp, tab)

    cov = np.zeros((5, 5))
    cov[np.ix_(free, free)] = _inverse(_hessian(nll_free, p5[free], steps[free]))
    sd = {n: _root(v) for n, v in zip(("shift", "sigma", "tail_fraction", "tail_decay",
                                       "signal_scale"), np.diag(cov))}
    g = np.array([0.0, 0.0, p[3], p[2], 0.0])
    lo, hi = _profile_interval(data, scale, p, nll, _root(float(g @ cov @ g)))
    sd["mean_delay"] = 0.5 * (hi - lo)
    s2 = np.maximum(data.signal * p[4] * _signal_pdf(x, *p[:4]), 1e-300)
    bshare = float(np.mean(data.background / (s2 + data.background)))
    sd["background"] = 0.0
    qv = quantum * quantum / 12.0
    core = math.sqrt(max(p[1] ** 2 - qv, 0.0))
    sd["sigma"] = sd["sigma"] * p[1] / core if core > 0 else math.inf
    return PulseFit(float(p[0]), core, float(p[2]), float(p[3]), float(p[2] * p[3]), bshare,
                    sd, cov, -float(nll), -float(nllg), math.sqrt(max(pg[1] ** 2 - qv, 0.0)),
                    int(x.size), float(quantum), (float(lo), float(hi)), float(p[4]))


def _inverse(H):
    try:
        return np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full(H.shape, np.inf)


def _root(v) -> float:
    return float(math.sqrt(v)) if v >= 0 else math.inf


def wall_return_residuals(prob, x, max_signal: float = 0.3):
    """The wall returns of a fitted calibration at low pile-up.

    ``prob`` : :class:`~mems_stereo.calib.problem.Problem` with its cells; ``x`` its
    fitted parameters.  For every cell whose expected signal photons ``m`` (the
    spot's share on the pixel) are at most ``max_signal`` and that fired inside its
    window: its time less the predicted return time τ, with m, its background rate
    and its window's end.  Returns (:class:`ReturnSamples`, window (lo, hi)), the
    window −6σ … +8σ of the pulse (σ: the calibration's, also the core σ held),
    each cell's end at most its ``t_max``; :func:`fit_pulse_shape` fits them by
    the first-photon law.
    """
    from mems_stereo.calib.problem import spot_share

    lay = prob.layout
    _, walls = lay.unpack(x)
    lo, hi = -6.0 * prob.sigma, 8.0 * prob.sigma
    parts = []
    for j in range(lay.T):
        c = prob.cells[j]
        pred, ok, _ = prob.predictions(x, j, c.shots)
        pos = np.searchsorted(c.shots, c.shot)
        pc = pred[pos]
        if prob.pixel_offsets is not None:
            W = prob.system.receiver.width
            pc[:, 0] += prob.pixel_offsets[(c.row * W + c.col).astype(np.int64)]
        s = min(max(math.exp(walls[j, 4]), 0.12), 6.0)
        m = np.exp(walls[j, 3] + pc[:, 3] - c.log_gref) * spot_share(c.col, pc[:, 1], s)[0]
        r = c.t - pc[:, 0]
        up = np.minimum(hi, c.t_max - pc[:, 0])
        sel = (ok[pos] & np.isfinite(r) & (m <= max_signal) & (m > 0.01 * max_signal)
               & (r >= lo) & (r <= up) & (up > lo + prob.sigma))
        parts.append((r[sel], m[sel], c.lam[sel], up[sel]))
    cat = [np.concatenate([q[i] for q in parts]) if parts else np.zeros(0) for i in range(4)]
    return ReturnSamples(*cat, lower=lo, core=float(prob.sigma)), (lo, hi)
