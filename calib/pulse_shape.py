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
        interval (:func:`mems_stereo.calib.pulse_returns.fit_return_shape`; None
        for plain residuals).
    signal_scale : κ, the fitted factor on the cells' expected signal (1: plain).
    From wall returns (:mod:`~mems_stereo.calib.pulse_returns`) the fifth
    parameter of ``cov`` is κ, not the background share (``background`` then is
    the share of the used detections the background explains).
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
        return signal_pdf(np.asarray(x, dtype=np.float64), self.shift, s,
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


def signal_pdf(x, mu, s, w, tau):
    """Density (1/s) of (1 − w)·N(μ, s) + w·EMG(μ, s, τ) at x (s)."""
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


def numerical_hessian(f, p, steps):
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
        return time, of signal cells at low pile-up (see module docstring); wall
        returns with their signal and window are fitted by the first-photon law
        (:mod:`mems_stereo.calib.pulse_returns`).
    window : (lo, hi) s analysed (default the residuals' range); residuals
        outside are dropped; background is uniform over it.
    quantum : s, the TDC bin width (its uniform spread is folded into the core).

    Returns
    -------
    PulseFit.  Raises :class:`~mems_stereo.errors.ShapeError` with fewer than
    :data:`MIN_SAMPLES` residuals.
    """
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
    H = numerical_hessian(lambda pp: _negloglik(pp, hist), p, steps)
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
