"""The pulse shape from wall returns by the first-photon law (``--model full``'s shape fit).

:func:`wall_return_residuals` takes a fitted wall calibration's low-pile-up cells
that fired: each detection's time less the predicted return time, with the cell's
expected signal photons m, background rate β and window [lo, hi] (cells end at
their ``t_max``).  :func:`fit_return_shape` fits the ex-Gaussian pulse of
:mod:`mems_stereo.calib.pulse_shape` to them by the exact law of a cell's first
detection (pile-up, background before the return and each window included); the
mean delay's σ from its profile likelihood.
:func:`fit_pulse_shape` takes either these samples or plain residuals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.pulse_shape import (
    MIN_SAMPLES,
    PulseFit,
    numerical_hessian,
    signal_pdf,
)
from mems_stereo.calib.pulse_shape import fit_pulse_shape as fit_residuals
from scipy import optimize, special

from mems_stereo.errors import ShapeError
from mems_stereo.physics.pulse import emg_cdf, emg_pdf


def fit_pulse_shape(residuals, *, window=None, quantum: float = 0.0) -> PulseFit:
    """:func:`fit_return_shape` of :class:`ReturnSamples`, else
    :func:`mems_stereo.calib.pulse_shape.fit_pulse_shape` of plain residuals."""
    if isinstance(residuals, ReturnSamples):
        return fit_return_shape(residuals, quantum)
    return fit_residuals(residuals, window=window, quantum=quantum)


@dataclass(frozen=True)
class ReturnSamples:
    """Wall returns for the first-photon shape fit (:func:`fit_return_shape`), one
    entry per cell that fired inside its window.

    residual : (N,) s, the detection's time less the predicted return time.
    signal : (N,) expected signal photons of the cell (the calibration's m).
    background : (N,) Hz, the cell's background rate.
    upper : (N,) s, the window's upper end for that cell (residual scale: codes
        after the cells' ``t_max`` are not recorded).
    lower : s, or (N,) s per cell, the window's lower end (the pixel is armed
        there: no earlier than the TDC's start).
    core : s or None, the Gaussian core's σ held fixed (the system's pulse σ with
        jitter: the ex-gaussian model's core is ``pulse_fwhm``), None: fitted.
    """

    residual: np.ndarray
    signal: np.ndarray
    background: np.ndarray
    upper: np.ndarray
    lower: float | np.ndarray
    core: float | None = None


#: signal scale κ beyond which (or below its inverse) the first-photon law does not
#: describe the returns: the mean delay's interval is then widened to reach 0
MISFIT_SCALE = 2.0
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
        low = np.broadcast_to(np.asarray(data.lower, dtype=np.float64), data.residual.shape)
        start = float(np.min(low)) if low.size else float(np.min(data.lower))
        n = int(min(FP_GRID, max(200, FP_STEPS * (top - start) / scale)))
        self.grid = np.linspace(start, top, n)
        h = self.grid[1] - self.grid[0]
        self.at = [self._weights(v, h) for v in (data.residual, data.upper, low)]
        self.bx = data.background * (data.residual - low)
        self.bh = data.background * (data.upper - low)

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
        ep, ec = emg_pdf(grid - mu, s, tau), emg_cdf(grid - mu, s, tau)
        Fg, fg = (1.0 - w) * Fg + w * ec, (1.0 - w) * fg + w * ep
    FL = tab.lookup(Fg, 2)
    F, FH, f = tab.lookup(Fg, 0) - FL, tab.lookup(Fg, 1) - FL, tab.lookup(fg, 0)
    with np.errstate(divide="ignore"):
        ll = (np.log(np.maximum(m * f + b, 1e-300)) - m * F - tab.bx
              - np.log(np.maximum(-np.expm1(-m * FH - tab.bh), 1e-300)))
    v = -float(np.sum(ll))
    return v if np.isfinite(v) else np.inf


def _fp_fit(data: ReturnSamples, scale: float, starts, mode):
    """Best of several starts of the first-photon fit; ``mode`` "gauss" (w = 0),
    "tail", or a fixed mean delay d (s, w = d/τ).  Returns natural p, −log L, z."""
    width = (float(np.max(data.upper)) - float(np.min(data.lower))) / scale
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
    local curvature understates how far the data allow it to go.  A fitted κ
    beyond :data:`MISFIT_SCALE` (or below its inverse) says the law does not
    describe the returns (as with windows that start before the TDC does: κ
    3.7–5, a core narrower than the pulse's); the interval then reaches 0.
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
    cov[np.ix_(free, free)] = _inverse(numerical_hessian(nll_free, p5[free], steps[free]))
    sd = {n: _root(v) for n, v in zip(("shift", "sigma", "tail_fraction", "tail_decay",
                                       "signal_scale"), np.diag(cov))}
    g = np.array([0.0, 0.0, p[3], p[2], 0.0])
    lo, hi = _profile_interval(data, scale, p, nll, _root(float(g @ cov @ g)))
    if not 1.0 / MISFIT_SCALE <= p[4] <= MISFIT_SCALE:  # the cells' signal does not
        lo = min(lo, 0.0)                                # describe their returns
    sd["mean_delay"] = 0.5 * (hi - lo)
    s2 = np.maximum(data.signal * p[4] * signal_pdf(x, *p[:4]), 1e-300)
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
    window −6σ … +8σ of the pulse (σ: the calibration's), each cell's start no
    earlier than the TDC's (a near wall's early photons are not recorded) and its
    end at most its ``t_max``; :func:`fit_pulse_shape` fits them by the
    first-photon law, the core σ free.
    """
    from mems_stereo.calib.pixel_offsets import cell_signal

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
        m = cell_signal(c, pc, walls[j, 3], walls[j, 4], lay.two_d, prob.pitch_ratio)
        r = c.t - pc[:, 0]
        up = np.minimum(hi, c.t_max - pc[:, 0])
        low = np.maximum(lo, -pc[:, 0])  # the pixel is armed from the TDC's start
        sel = (ok[pos] & np.isfinite(r) & (m <= max_signal) & (m > 0.01 * max_signal)
               & (r >= low) & (r <= up) & (up > low + prob.sigma))
        parts.append((r[sel], m[sel], c.lam[sel], up[sel], low[sel]))
    cat = [np.concatenate([q[i] for q in parts]) if parts else np.zeros(0) for i in range(5)]
    return ReturnSamples(*cat[:4], lower=cat[4]), (lo, hi)
