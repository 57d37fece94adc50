"""The likelihood fit of :mod:`mems_stereo.calib.problem` from start values.

* :func:`build_cells` — each wall's cells around the beam's predicted image
  (:func:`mems_stereo.calib.association.cells_near_track`);
* :func:`newton` — damped Newton (BHHH / Levenberg) ascent of the likelihood;
* :func:`solve` — rounds of both, the cells re-centred on the fitted image;
* :func:`leave_one_out` — each measured distance against a fit without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.association import cells_near_track
from mems_stereo.calib.problem import Layout, Problem, distance_model

from mems_stereo.errors import GeometryError, NotObservableError
from mems_stereo.model.system import System

N_ROUNDS = 2
MAX_ITER = 100


class FitState:
    """The solver's state (for diagnostics): Newton iterations so far, whether the
    last run converged, and why not."""

    def __init__(self):
        self.iterations = 0
        self.converged = False
        self.message = ""


@dataclass(frozen=True, slots=True)
class FitSetup:
    """What every likelihood fit of one calibration shares.

    system : the nominal System (its fixed parts hold; free values start from it).
    names : free system parameters (names of
        :data:`~mems_stereo.calib.model.SYSTEM_PARAMS`, in that order).
    two_d : True for a 2-D sensor (the walls' β is fitted too).
    sigma : s, the pulse's σ with the timing jitter.
    """

    system: System
    names: list[str]
    two_d: bool
    sigma: float


@dataclass(frozen=True, slots=True)
class StartValues:
    """Where a fit starts (or a fit's outcome as the next one's start): ``values``
    dict name → SI value of the system parameters, ``walls`` (T, 5) float64 per
    wall α (rad), β (rad), D (m), log μ (μ: signal photons per shot), log s (s:
    spot σ, px)."""

    values: dict[str, float]
    walls: np.ndarray


@dataclass(frozen=True, slots=True)
class NewtonResult:
    """Where :func:`newton` stopped: ``x`` (P,) SI parameter vector, ``loglik`` its
    log-likelihood, ``grad`` (P,) the score and ``info`` (P, P) SI the outer-product
    information there."""

    x: np.ndarray
    loglik: float
    grad: np.ndarray
    info: np.ndarray


@dataclass(frozen=True, slots=True)
class Solution:
    """A likelihood fit: the :class:`~mems_stereo.calib.problem.Problem` (with the
    cells it ended on), ``x`` (P,) SI its parameter vector and ``info`` (P, P) SI
    the outer-product information at ``x``."""

    problem: Problem
    x: np.ndarray
    info: np.ndarray


@dataclass(frozen=True, slots=True)
class LeftOut:
    """One measured distance against a fit without it (:func:`leave_one_out`).

    wall : index of the wall; kind : "axis" | "normal"; measured, measured_std : m;
    fitted, fitted_std : m, the wall's distance fitted without the measurement
    and its σ; loglik : log-likelihood of the data and the other distances then.
    """

    wall: int
    kind: str
    measured: float
    measured_std: float
    fitted: float
    fitted_std: float
    loglik: float


def build_cells(prob: Problem, x, radius: int):
    """Each wall's cells within ``radius`` pixels of the beam's image at ``x`` (in place);
    log μ_j re-referenced to the new cells.  Returns ``x``.  Raises
    :class:`NotObservableError` naming a wall whose fitted beam misses the sensor."""
    lay = prob.layout
    _, walls = lay.unpack(x)
    window = prob.system.tdc.n_bins * prob.system.tdc.bin_width
    for j, w in enumerate(prob.walls):
        pred, ok, _ = prob.predictions(x, j)
        W = prob.system.receiver.width
        on = ok & (pred[:, 1] > -0.5) & (pred[:, 1] < W - 0.5)
        if not on.any():
            raise NotObservableError(f"{w.source}: the fitted beam never meets the sensor")
        t_max = min(float(np.max(pred[on, 0])) + 6.0 * prob.sigma, window)
        lgref = float(np.median(pred[on, 3]))
        old = prob.cells[j]
        if old is not None:  # keep μ_k: log μ_j is relative to the reference
            x[lay.wall_slice(j).start + lay.wall_names.index("logmu")] += lgref - old.log_gref
        prob.cells[j] = cells_near_track(w, pred, ok, radius, t_max, lgref, lay.two_d)
    return x


def newton(prob: Problem, x, state: FitState, max_iter: int = MAX_ITER,
           tol: float = 1e-3) -> NewtonResult:
    """Damped Newton ascent with the outer-product information (BHHH/Levenberg)."""
    sc = prob.layout.scales
    lam = 1e-3
    ll, g, H = prob.score(x)
    for _ in range(max_iter):
        state.iterations += 1
        gs = g * sc
        Hs = H * sc[:, None] * sc[None, :]
        dH = np.maximum(np.diag(Hs), 1e-12)
        improved = False
        for _ in range(12):
            try:
                step = np.linalg.solve(Hs + lam * np.diag(dH), gs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = x + step * sc
            try:
                lln = prob.loglik(xn)
            except GeometryError:  # a trial step outside the model (e.g. a harmonic so
                lln = -math.inf    # strong the mirror turns back): damp and retry
            if np.isfinite(lln) and lln >= ll - 1e-9:
                improved = True
                break
            lam *= 10
        if not improved:
            state.message = "no step increases the likelihood"
            return NewtonResult(x, ll, g, H)
        expected = float(gs @ step)
        x = xn
        lam = max(lam / 5, 1e-6)
        ll, g, H = prob.score(x)
        if expected < tol:
            state.converged = True
            return NewtonResult(x, ll, g, H)
    state.message = f"no convergence in {max_iter} iterations"
    return NewtonResult(x, ll, g, H)


def leave_one_out(prob: Problem, x, lay: Layout) -> list[LeftOut]:
    """A :class:`LeftOut` for each measured distance: the wall's distance as fitted
    without that measurement (from the full fit's solution), and the
    log-likelihood of the data and the other distances then."""
    priors = list(prob.priors)
    out = []
    try:
        for i, (j, kind, d, sd) in enumerate(priors):
            prob.priors = priors[:i] + priors[i + 1:]
            st = FitState()
            nr = newton(prob, x.copy(), st, max_iter=30)
            cov, _, _ = obs.covariance(nr.info, lay.scales)
            _, wp = lay.unpack(nr.x)
            f = distance_model(wp[j], kind)
            ws = lay.wall_slice(j)
            g = np.zeros(lay.size)
            for q, pn in enumerate(lay.wall_names):
                if pn in ("alpha", "beta", "dist"):
                    w2 = wp[j].copy()
                    w2[{"alpha": 0, "beta": 1, "dist": 2}[pn]] += 1e-7
                    g[ws.start + q] = (distance_model(w2, kind) - f) / 1e-7
            c = np.where(np.isfinite(cov), cov, 1e6)
            out.append(LeftOut(j, kind, d, sd, f, math.sqrt(max(float(g @ c @ g), 0.0)),
                               nr.loglik))
    finally:
        prob.priors = priors
    return out


def solve(setup: FitSetup, walls, priors, values: dict, wall_p: np.ndarray, state: FitState,
          progress=None) -> Solution:
    """Likelihood fit rounds from start values.

    walls : the :class:`~mems_stereo.calib.problem.WallData` fitted; priors :
    [(wall index, kind, distance m, σ m)]; values : dict name → SI start value (at
    least ``setup.names``); wall_p : (T, 5) start walls (α rad, β rad, D m, log μ,
    log s); state : updated in place; progress : optional callable(str).
    """
    names = setup.names
    lay = Layout(names, len(walls), setup.two_d)
    prob = Problem(walls, setup.system, lay, setup.sigma, priors)
    x = lay.pack({n: values[n] for n in names}, wall_p)
    H = None
    for rnd in range(N_ROUNDS):
        x = build_cells(prob, x, radius=3 if rnd == 0 else 2)
        state.converged = False
        nr = newton(prob, x, state)
        x, H = nr.x, nr.info
        if progress:
            v, _ = lay.unpack(x)
            progress(f"round {rnd + 1}: log-likelihood {nr.loglik:.1f}, "
                     + ", ".join(f"{n} {obs.fmt(n, v[n])}" for n in names))
        if not state.converged:  # no point re-centring a fit that went nowhere
            break
    return Solution(prob, x, H)
