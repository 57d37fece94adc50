"""The likelihood fit of :mod:`mems_stereo.calib.problem` from start values.

* :func:`build_cells` — each wall's cells around the beam's predicted image
  (:func:`mems_stereo.calib.association.cells_near_track`);
* :func:`newton` — damped Newton (BHHH / Levenberg) ascent of the likelihood;
* :func:`solve` — rounds of both, the cells re-centred on the fitted image;
* :func:`leave_one_out` — each measured distance against a fit without it.
"""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib import observability as obs
from mems_stereo.calib.association import cells_near_track
from mems_stereo.calib.problem import Layout, Problem, distance_model

from mems_stereo.errors import NotObservableError

N_ROUNDS = 2
MAX_ITER = 100


class FitState:
    """The solver's state (for diagnostics)."""

    def __init__(self):
        self.iterations = 0
        self.converged = False
        self.message = ""


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


def newton(prob: Problem, x, state: FitState, max_iter: int = MAX_ITER, tol: float = 1e-3):
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
            lln = prob.loglik(xn)
            if np.isfinite(lln) and lln >= ll - 1e-9:
                improved = True
                break
            lam *= 10
        if not improved:
            state.message = "no step increases the likelihood"
            return x, ll, g, H
        expected = float(gs @ step)
        x = xn
        lam = max(lam / 5, 1e-6)
        ll, g, H = prob.score(x)
        if expected < tol:
            state.converged = True
            return x, ll, g, H
    state.message = f"no convergence in {max_iter} iterations"
    return x, ll, g, H


def leave_one_out(prob: Problem, x, lay: Layout):
    """[(j, kind, d, σ_d, fitted, σ_fitted, log-likelihood)] for each measured distance:
    the wall's distance as fitted without that measurement (from the full fit's
    solution), and the log-likelihood of the data and the other distances then."""
    priors = list(prob.priors)
    out = []
    try:
        for i, (j, kind, d, sd) in enumerate(priors):
            prob.priors = priors[:i] + priors[i + 1:]
            st = FitState()
            xi, ll_i, _, H = newton(prob, x.copy(), st, max_iter=30)
            cov, _, _ = obs.covariance(H, lay.scales)
            _, wp = lay.unpack(xi)
            f = distance_model(wp[j], kind)
            ws = lay.wall_slice(j)
            g = np.zeros(lay.size)
            for q, pn in enumerate(lay.wall_names):
                if pn in ("alpha", "beta", "dist"):
                    w2 = wp[j].copy()
                    w2[{"alpha": 0, "beta": 1, "dist": 2}[pn]] += 1e-7
                    g[ws.start + q] = (distance_model(w2, kind) - f) / 1e-7
            c = np.where(np.isfinite(cov), cov, 1e6)
            out.append((j, kind, d, sd, f, math.sqrt(max(float(g @ c @ g), 0.0)), ll_i))
    finally:
        prob.priors = priors
    return out


def solve(walls, system, names, two_d, sigma, priors, values, wall_p, state, progress):
    """Likelihood fit rounds from start values: (problem, x, information)."""
    lay = Layout(names, len(walls), two_d)
    prob = Problem(walls, system, lay, sigma, priors)
    x = lay.pack({n: values[n] for n in names}, wall_p)
    H = None
    for rnd in range(N_ROUNDS):
        x = build_cells(prob, x, radius=3 if rnd == 0 else 2)
        state.converged = False
        x, ll, g, H = newton(prob, x, state)
        if progress:
            v, _ = lay.unpack(x)
            progress(f"round {rnd + 1}: log-likelihood {ll:.1f}, "
                     + ", ".join(f"{n} {obs.fmt(n, v[n])}" for n in names))
        if not state.converged:  # no point re-centring a fit that went nowhere
            break
    return prob, x, H
