"""Expected (Fisher) information of the first-photon cells, for the flat-wall
consistency test.

A cell (shot k, pixel c) observes its first photon on [0, T] under the intensity
``I(t) = λ + m·φ((t − τ)/σ)/σ`` (:mod:`mems_stereo.calib.problem`).  Every score
of the cell is a combination of its two scores ∂ℓ/∂τ and ∂ℓ/∂m:
``∂ℓ/∂θ = a_θ·∂ℓ/∂τ + b_θ·∂ℓ/∂m`` with ``a_θ = ∂τ/∂θ`` and ``b_θ = ∂m/∂θ``.
The expected information of (τ, m) of a censored first event with hazard I is

    F_ij = ∫₀^T ∂_i I · ∂_j I / I · S(t) dt,   S(t) = exp(−∫₀ᵗ I),

so the information of any parameters follows from per-cell 2×2 matrices
(:func:`cell_fisher`) and the rows ``a``, ``b`` (:func:`wall_rows`).

Why not the outer product of the observed scores (what the solver uses): a
weak wall has a few hundred signal cells, and the outer product's estimate of
the information left to a quarter-sensor time shift once the wall's pose, the
offset and the baseline are fitted (a small difference of large numbers) is
then dominated by a handful of cells — the test statistic becomes heavy-tailed
and correct fits fail it.  The expected information has no such noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib.problem import SPOT_MAX, SPOT_MIN, pulse_at, spot_px, spot_share
from scipy.special import ndtr

_SQ2PI = math.sqrt(2.0 * math.pi)
#: pulse σ on each side of the return covered by the integral, and grid points
Z_SPAN = 7.0
N_GRID = 71
CHUNK = 16384


def cell_fisher(tau: np.ndarray, m: np.ndarray, lam: np.ndarray, t_max: float,
                sigma: float, pulse=None) -> np.ndarray:
    """(N, 3) expected information [F_ττ, F_τm, F_mm] of each cell, SI (s⁻², s⁻¹, 1).

    tau : (N,) s, return centre; m : (N,) signal photons of the cell; lam : (N,)
    Hz background; t_max : s, end of the analysed window; sigma : s, pulse σ;
    pulse : None (Gaussian) or the ex-gaussian tail (w, τ_d) (:func:`shaped_fisher`).
    The signal part of the intensity is zero outside τ ± ``Z_SPAN``·σ, where
    ∂I/∂τ and ∂I/∂m vanish, so the integral runs over that span only
    (trapezoid rule on ``N_GRID`` points over that span clipped to [0, T]).
    """
    if pulse is not None:
        return shaped_fisher(tau, m, lam, t_max, sigma, pulse)
    tau = np.asarray(tau, dtype=np.float64)
    out = np.zeros((tau.size, 3))
    g01 = np.linspace(0.0, 1.0, N_GRID)
    w01 = np.full(N_GRID, 1.0 / (N_GRID - 1))
    w01[[0, -1]] *= 0.5
    for a in range(0, tau.size, CHUNK):
        sl = slice(a, a + CHUNK)
        tt, mm, ll = tau[sl, None], np.asarray(m)[sl, None], np.asarray(lam)[sl, None]
        z0 = -tt / sigma
        # the span [τ − Z_SPAN σ, τ + Z_SPAN σ] clipped to the window [0, T]
        lo = np.clip(z0, -Z_SPAN, Z_SPAN)
        hi = np.clip((t_max - tt) / sigma, -Z_SPAN, Z_SPAN)
        width = np.maximum(hi - lo, 0.0)
        z = lo + width * g01[None, :]
        t = tt + sigma * z
        phi = np.exp(-0.5 * z * z) / _SQ2PI
        cum = ll * t + mm * (ndtr(z) - ndtr(z0))
        surv = np.exp(-cum)
        inten = np.maximum(ll + mm * phi / sigma, 1e-300)
        dt_ = mm * z * phi / (sigma * sigma)
        dm_ = phi / sigma
        w = surv / inten * (sigma * width) * w01[None, :]
        out[sl, 0] = np.sum(w * dt_ * dt_, axis=1)
        out[sl, 1] = np.sum(w * dt_ * dm_, axis=1)
        out[sl, 2] = np.sum(w * dm_ * dm_, axis=1)
    return out


def shaped_fisher(tau, m, lam, t_max: float, sigma: float, pulse) -> np.ndarray:
    """:func:`cell_fisher` with the ex-gaussian pulse (w, τ_d) of
    :func:`mems_stereo.calib.problem.shaped_terms`: the span runs to
    τ + ``Z_SPAN``·σ + 12 τ_d, on 2·``N_GRID`` points."""
    w, tau_d = float(pulse[0]), float(pulse[1])
    tau = np.asarray(tau, dtype=np.float64)
    out = np.zeros((tau.size, 3))
    n = 2 * N_GRID
    g01 = np.linspace(0.0, 1.0, n)
    w01 = np.full(n, 1.0 / (n - 1))
    w01[[0, -1]] *= 0.5
    for a in range(0, tau.size, CHUNK // 2):
        sl = slice(a, a + CHUNK // 2)
        tt, mm, ll = tau[sl, None], np.asarray(m)[sl, None], np.asarray(lam)[sl, None]
        lo = np.clip(tt - Z_SPAN * sigma, 0.0, t_max)
        hi = np.clip(tt + Z_SPAN * sigma + 12.0 * tau_d, 0.0, t_max)
        width = np.maximum(hi - lo, 0.0)
        t = lo + width * g01[None, :]
        p = pulse_at(t - tt, sigma, w, tau_d)
        f, slope = p.pdf, p.slope
        surv = np.exp(-(ll * t + mm * (p.cdf - pulse_at(-tt, sigma, w, tau_d).cdf)))
        inten = np.maximum(ll + mm * f, 1e-300)
        dt_ = -mm * slope
        wt = surv / inten * width * w01[None, :]
        out[sl, 0] = np.sum(wt * dt_ * dt_, axis=1)
        out[sl, 1] = np.sum(wt * dt_ * f, axis=1)
        out[sl, 2] = np.sum(wt * f * f, axis=1)
    return out


@dataclass(frozen=True, slots=True)
class WallRows:
    """Per-cell chain rows of one wall (:func:`wall_rows`), N cells, G geometry
    parameters.

    m : (N,) float64, the cell's signal photons (0 where the prediction fails).
    a : (N, G + 2) float64, ∂τ/∂θ (s per parameter unit) for the geometry
        parameters, log μ and log s (the order of
        :meth:`~mems_stereo.calib.problem.Problem.wall_terms`).
    b : (N, G + 2) float64, ∂m/∂θ (photons per parameter unit), same columns.
    bu : (N,) float64, ∂m/∂u (photons per px): the column-shift direction of the
        consistency test.
    """

    m: np.ndarray
    a: np.ndarray
    b: np.ndarray
    bu: np.ndarray


def wall_rows(cells, pred: np.ndarray, ok: np.ndarray, Jc: np.ndarray, logmu: float,
              logspot: float, two_d: bool, pitch_ratio: float = 1.0) -> WallRows:
    """Per-cell chain rows of one wall (a :class:`WallRows`).

    cells : :class:`~mems_stereo.calib.problem.Cells`; pred : (N, 4) per-cell
    [τ, u, v, log g]; ok : (N,) bool; Jc : (N, 4, G) ∂[τ, u, v, log g]/∂(geometry
    parameters); logmu, logspot : the wall's log μ and log s (s: spot σ, px).
    """
    u, v, lg = pred[:, 1], pred[:, 2], pred[:, 3]
    s = spot_px(logspot)
    mu = np.exp(logmu + lg - cells.log_gref)
    f, fu, fs = spot_share(cells.col, u, s)
    if two_d:
        fr, fv, frs = spot_share(cells.row, v, s * pitch_ratio)
        share, dsu, dsv, dss = f * fr, fu * fr, f * fv, fs * fr + f * frs
    else:
        share, dsu, dsv, dss = f, fu, np.zeros_like(fu), fs
    okf = ok.astype(np.float64)
    m = np.where(ok, mu * share, 0.0)
    G = Jc.shape[2]
    a = np.zeros((m.size, G + 2))
    b = np.zeros((m.size, G + 2))
    a[:, :G] = Jc[:, 0, :] * okf[:, None]
    b[:, :G] = ((mu * dsu)[:, None] * Jc[:, 1, :] + (mu * dsv)[:, None] * Jc[:, 2, :]
                + m[:, None] * Jc[:, 3, :]) * okf[:, None]
    b[:, G] = m
    b[:, G + 1] = mu * dss * okf * (1.0 if SPOT_MIN < s < SPOT_MAX else 0.0)
    bu = np.where(ok, mu * dsu, 0.0)
    return WallRows(m, a, b, bu)


def information(F: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, P) Σ over cells of [a b] F [a b]ᵀ: F (N, 3), a and b (N, P)."""
    Fa = F[:, 0:1] * a + F[:, 1:2] * b
    Fb = F[:, 1:2] * a + F[:, 2:3] * b
    return a.T @ Fa + b.T @ Fb


def consistency_information(cells, pc: np.ndarray, ok: np.ndarray, Jc: np.ndarray,
                            wall: np.ndarray, sigma: float, two_d: bool,
                            pitch_ratio: float = 1.0, width: int = 192,
                            pulse=None) -> np.ndarray:
    """(8 + G + 2, 8 + G + 2) expected information of one wall's cells for
    :func:`mems_stereo.calib.observability.consistency_scores`: a TDC-time shift
    per quarter of the sensor (4), a column shift per quarter (4), then the
    wall's nuisance in the order of
    :meth:`~mems_stereo.calib.problem.Problem.wall_terms` (G geometry
    parameters, log μ, log s).

    pc : (N, 4) per-cell [τ, u, v, log g] (placeholder rows where not ``ok``);
    ok : (N,) bool; Jc : (N, 4, G) their Jacobian; wall : (5,) α, β, D, log μ,
    log s; sigma : s, pulse σ; width : sensor columns; pulse : None or the
    ex-gaussian tail (w, τ_d).
    """
    rows = wall_rows(cells, pc, ok, Jc, wall[3], wall[4], two_d, pitch_ratio)
    m, a, b, bu = rows.m, rows.a, rows.b, rows.bu
    F = cell_fisher(pc[:, 0], m, cells.lam, cells.t_max, sigma, pulse)
    q = np.clip((cells.col / width * 4).astype(np.int64), 0, 3)
    aE = np.zeros((m.size, 8))
    bE = np.zeros((m.size, 8))
    okf = ok.astype(np.float64)
    for i in range(4):
        aE[:, i] = (q == i) * okf
        bE[:, 4 + i] = (q == i) * bu
    return information(F, np.hstack([aE, a]), np.hstack([bE, b]))


def expected_information(prob, x) -> np.ndarray:
    """(P, P) SI expected information of the whole problem at ``x`` (all walls'
    cells, plus the measured distances' Gauss-Newton term): the counterpart of
    :meth:`~mems_stereo.calib.problem.Problem.score`'s outer product."""
    lay = prob.layout
    values, walls = lay.unpack(x)
    H = np.zeros((lay.size, lay.size))
    for j in range(lay.T):
        c = prob.cells[j]
        pred, ok, (J, geo) = prob.predictions(x, j, c.shots, steps=True)
        pos = np.searchsorted(c.shots, c.shot)
        pc = np.where(ok[pos, None], pred[pos], [0.0, -1e6, -1e6, 0.0])
        rows = wall_rows(c, pc, ok[pos], J[pos], walls[j, 3], walls[j, 4], lay.two_d,
                         prob.pitch_ratio)
        m, a, b = rows.m, rows.a, rows.b
        ws = lay.wall_slice(j)
        idx = geo + [ws.start + lay.wall_names.index("logmu"),
                     ws.start + lay.wall_names.index("logspot")]
        F = cell_fisher(pc[:, 0], m, c.lam, c.t_max, prob.sigma, prob.pulse(values))
        H[np.ix_(idx, idx)] += information(F, a, b)
    return H + prob.prior_terms(x)[2]
