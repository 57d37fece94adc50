"""The goodness-of-fit tests' null distribution on a given design, by drawing cells.

:func:`resampled` redraws every analysed cell's first detection from the model at the
fitted ``x`` (the same shots, pixels, background rates and windows; a fresh outcome
per cell): under such data each cell's score has exactly the law the tests assume,
and the p-values of :func:`mems_stereo.calib.goodness.calibration_goodness` on many
replicas (:func:`null_pvalues`, no refit) show whether the tests' reference
distribution holds for this design — heavy-tailed scores of weakly lit groups, an
approximate information — apart from the fit's own projection (which, in a linear
model, can only make a test conservative).

A cell (shot k, pixel c) sees the intensity ``I(t) = λ + m·f(t − τ)`` on [0, T]
(:mod:`mems_stereo.calib.problem`); its first event is drawn by inversion of the
integrated intensity ``Λ(t) = λt + m·(P(t − τ) − P(−τ))`` (P the pulse's
distribution function): with E ~ Exp(1), t = Λ⁻¹(E), no event where Λ(T) < E.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
from mems_stereo.calib.problem import Problem, pulse_at, spot_px, spot_share
from scipy.special import ndtr

#: bisection steps of the inversion (the window over 2⁶⁰: far below a TDC code)
BISECT = 60


def cell_model(prob: Problem, x, j: int) -> tuple:
    """Wall j's cells under the model at ``x``: (τ (N,) s, m (N,) expected signal
    photons of the cell, pulse (None: Gaussian of σ ``prob.sigma``, or (w, τ_d)));
    cells whose prediction fails get m = 0."""
    lay = prob.layout
    values, walls = lay.unpack(x)
    c = prob.cells[j]
    pred, ok, _ = prob.predictions(x, j, c.shots)
    pos = np.searchsorted(c.shots, c.shot)
    good = ok[pos]
    pc = np.where(good[:, None], pred[pos], [0.0, -1e6, -1e6, 0.0])
    if prob.pixel_offsets is not None:
        W = prob.system.receiver.width
        pc[:, 0] += prob.pixel_offsets[(c.row * W + c.col).astype(np.int64)]
    s = spot_px(walls[j, 4])
    share, _, _ = spot_share(c.col, pc[:, 1], s)
    if lay.two_d:
        share = share * spot_share(c.row, pc[:, 2], s * prob.pitch_ratio)[0]
    mu = np.exp(walls[j, 3] + pc[:, 3] - c.log_gref)
    return pc[:, 0], np.where(good, mu * share, 0.0), prob.pulse(values)


def _cdf(dt, sigma: float, pulse):
    if pulse is None:
        return ndtr(dt / sigma)
    return pulse_at(dt, sigma, float(pulse[0]), float(pulse[1])).cdf


def first_events(tau, m, lam, t_max: float, sigma: float, pulse, rng) -> np.ndarray:
    """(N,) s, each cell's first event on [0, ``t_max``] under I(t) = λ + m·f(t − τ)
    (see the module), NaN where none.  tau, m, lam : (N,) s, photons, Hz."""
    tau, m, lam = (np.asarray(a, dtype=np.float64) for a in (tau, m, lam))
    p0 = _cdf(-tau, sigma, pulse)

    def big_lambda(t):
        return lam * t + m * (_cdf(t - tau, sigma, pulse) - p0)

    e = rng.exponential(1.0, tau.size)
    fired = big_lambda(np.full(tau.size, t_max)) >= e
    lo, hi = np.zeros(tau.size), np.full(tau.size, float(t_max))
    for _ in range(BISECT):
        mid = 0.5 * (lo + hi)
        below = big_lambda(mid) < e
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return np.where(fired, 0.5 * (lo + hi), np.nan)


def resampled(prob: Problem, x, rng: np.random.Generator) -> Problem:
    """A copy of ``prob`` (cells built) whose cells' detections are drawn from the
    model at ``x`` (:func:`first_events`); everything else shared."""
    out = copy.copy(prob)
    out.cells = []
    for j, c in enumerate(prob.cells):
        tau, m, pulse = cell_model(prob, x, j)
        t = first_events(tau, m, c.lam, c.t_max, prob.sigma, pulse, rng)
        out.cells.append(replace(c, t=t))
    return out


def null_pvalues(prob: Problem, x, replicas: int, rng: np.random.Generator) -> dict:
    """Test name → (replicas,) p-values of
    :func:`~mems_stereo.calib.goodness.calibration_goodness` on cells drawn from the
    model at ``x`` (:func:`resampled`; names "time: <test>", "column: <test>")."""
    from mems_stereo.calib.goodness import calibration_goodness

    out: dict = {}
    for _ in range(replicas):
        for part, rep in zip(("time", "column"),
                             calibration_goodness(resampled(prob, x, rng), x)):
            for f in rep.findings:
                out.setdefault(f"{part}: {f.name}", []).append(f.p_value)
    return {k: np.asarray(v) for k, v in out.items()}
