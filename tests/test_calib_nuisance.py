"""Held hardware terms in the covariance (calib/nuisance.py): the sensitivity of a fit
to a term it holds against a refit with the term moved, and the one-step estimate of
the held term against the value in the data."""

from __future__ import annotations

import math

import numpy as np
from mems_stereo.calib.nuisance import edge_direction, held_sensitivity, profile_tail
from mems_stereo.calib.problem import Cells, Layout, Problem, WallData
from mems_stereo.calib.solver import FitState, newton

from mems_stereo.model.hardware import MonitorEdges
from mems_stereo.model.scanner import phase_from_zero_crossings
from mems_stereo.model.system import burkard2022

NAMES = ["theta0", "phase_offset", "tdc_offset", "harmonic2_cos", "harmonic2_sin"]
WALL = np.array([[0.0, 0.0, 1.5, math.log(0.3), math.log(0.6)]])


def _edges(system, difference: float):
    """``system`` whose monitor's rising edge is late by difference/2 and falling
    early by as much (the mean delay 0)."""
    from dataclasses import replace

    mon = MonitorEdges(0.5 * difference, -0.5 * difference)
    return system.replace(scanner=replace(system.scanner, monitor=mon))


def _problem(rng, difference: float = 0.0, n_shots: int = 10000, tail=None, names=NAMES):
    """One wall at 1.5 m: cells drawn from the model of a system with an edge-delay
    difference ``difference`` s (and a pulse tail ``tail`` = (share, decay s) on the
    1 ns Gaussian); the returned problem, free ``names``, holds them at 0."""
    f = 1570.0
    zc = np.arange(0, 0.2, 0.5 / f) + 1e-4
    rising = (np.arange(zc.size) % 2).astype(bool)
    t = np.sort(rng.uniform(zc[0] + 1e-5, zc[-1] - 1e-5, n_shots))
    sys0 = burkard2022()
    w = WallData(phase_from_zero_crossings(t, zc, rising)[0], np.zeros((n_shots, 1, 192),
                 np.uint16), np.full((1, 192), 1e5), 3.125e-10, "w", t, zc, rising)
    lay = Layout(NAMES, 1, False)
    x = lay.pack({n: sys0.get_param(n) for n in NAMES}, WALL)
    pred, ok, _ = Problem([w], _edges(sys0, difference), lay, 1e-9).predictions(x, 0)
    shots = np.flatnonzero(ok & (pred[:, 1] > 3) & (pred[:, 1] < 188))
    u = np.rint(pred[shots, 1])
    cols = (u[:, None] + np.arange(-2, 3)[None, :]).ravel()
    sh = np.repeat(shots, 5)
    share = np.exp(-0.5 * ((cols - pred[sh, 1]) / 0.6) ** 2) * 1.0 / (0.6 * np.sqrt(2 * np.pi))
    n = np.minimum(rng.poisson(share), 4)
    a = rng.normal(0.0, 1e-9, (sh.size, 4))  # the first of the n photons
    if tail is not None:
        a += np.where(rng.random((sh.size, 4)) < tail[0], rng.exponential(tail[1], a.shape), 0)
    a[np.arange(4)[None, :] >= n[:, None]] = np.inf
    times = np.where(n > 0, pred[sh, 0] + a.min(axis=1), np.nan)
    lay = Layout(names, 1, False)
    prob = Problem([w], sys0, lay, 1e-9)
    prob.cells[0] = Cells(sh, cols, np.zeros_like(cols), times, np.full(sh.size, 1e3), 60e-9,
                          shots, float(np.median(pred[shots, 3])))
    return prob, lay.pack({n: sys0.get_param(n) for n in names}, WALL)


def test_held_edge_sensitivity_matches_a_refit_with_the_edges_moved():
    """S·δ against the fit's move when the problem holds the edge-delay difference at
    δ instead of 0 (same data; first order, and the outer-product information for the
    Hessian: within 10 % of the largest move); the phase offset, which holds the mean
    of the two delays, hardly moves."""
    prob, x = _problem(np.random.default_rng(5))
    x0 = newton(prob, x, FitState()).x
    held = held_sensitivity(prob, x0, edge_direction(prob.system))
    delta = 300e-9
    moved = Problem(prob.walls, _edges(prob.system, delta), prob.layout, prob.sigma)
    moved.cells = prob.cells
    st = FitState()
    x1 = newton(moved, x0, st).x
    assert st.converged
    n = prob.layout.n_sys
    sd = np.sqrt(np.diag(held.C)[:n])
    step = (x1 - x0)[:n] / sd
    assert np.max(np.abs(step)) > 0.5, step  # θ0, tdc_offset, 2nd harmonic's cos
    np.testing.assert_allclose(step, held.S[:n] * delta / sd, atol=0.1 * np.max(np.abs(step)))
    assert abs(step[prob.layout.names.index("phase_offset")]) < 0.05
    # no edge difference in these data: its one-step estimate is within 3σ of 0
    assert abs(held.value) < 3 * held.std


def test_held_edge_estimate_recovers_the_difference_in_the_data():
    """Data from edges 400 ns apart, fitted holding them equal: the one-step estimate
    of the difference lies within 3σ of 400 ns."""
    prob, x = _problem(np.random.default_rng(6), 400e-9)
    x0 = newton(prob, x, FitState()).x
    held = held_sensitivity(prob, x0, edge_direction(prob.system))
    assert 0 < held.std < 400e-9
    assert abs(held.value - 400e-9) < 3 * held.std, (held.value, held.std)


def test_profile_tail_finds_the_share_at_the_right_decay():
    """A 30 % tail of 3 ns on the 1 ns pulse: the share fitted at the held decays is
    the truth's within 3σ at the decay of the data."""
    prob, x = _problem(np.random.default_rng(7), tail=(0.3, 3e-9),
                       names=["theta0", "tdc_offset"])
    x0 = newton(prob, x, FitState()).x
    prof = profile_tail(prob, x0)
    assert prof is not None and prof.decay == 3e-9
    assert abs(prof.share - 0.3) < 3 * prof.share_std, prof
    # the Gaussian fit's TDC offset misses the pulse's mean delay 0.9 ns; the profile
    # fit's (its offset less the move) holds it
    bias = x0[1] - 0.9e-9
    assert abs(x0[1] - prof.move[1] - 0.9e-9) < 0.5 * abs(bias)
