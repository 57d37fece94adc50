"""The start of a newly selected hardware block (calib/full_model.newton_start):
the score test's Newton step, with the fall back to 0."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.calib import full_model as fm
from mems_stereo.calib.hardware_fit import candidate_blocks, extended_problem, score_tests
from mems_stereo.calib.model import harmonic_orders
from mems_stereo.calib.problem import Cells, Layout, Problem
from mems_stereo.calib.solver import FitState, newton
from test_hardware_fit import blank_wall

from mems_stereo.model.system import burkard2022

H3 = harmonic_orders((3,))
#: the drawn wall's third harmonic (cos, sin), relative amplitude
TRUE_H3 = (0.004, -0.002)


def _drawn(seed: int, harmonic=TRUE_H3):
    """A wall whose first photons are drawn from the model with a third harmonic
    ``harmonic`` (cos, sin) in the mirror's motion, and the ideal model's fit of it
    (θ0, TDC offset and the wall free): (problem, x at that fit)."""
    rng = np.random.default_rng(seed)
    sys0 = burkard2022()
    w = blank_wall(rng, 6000)
    names = ["theta0", "tdc_offset"]
    true_lay = Layout(names + H3, 1, False)
    prob_t = Problem([w], sys0, true_lay, 1e-9)
    wall = np.array([[0.0, 0.0, 1.5, np.log(0.3), np.log(0.6)]])
    vals = {"theta0": sys0.scanner.theta0, "tdc_offset": 0.0,
            H3[0]: harmonic[0], H3[1]: harmonic[1]}
    pred, ok, _ = prob_t.predictions(true_lay.pack(vals, wall), 0)
    shots = np.flatnonzero(ok & (pred[:, 1] > 3) & (pred[:, 1] < 188))
    cols = (np.rint(pred[shots, 1])[:, None] + np.arange(-2, 3)[None, :]).ravel()
    sh = np.repeat(shots, 5)
    share = np.exp(-0.5 * ((cols - pred[sh, 1]) / 0.6) ** 2) * 0.3 / (0.6 * np.sqrt(2 * np.pi))
    n = rng.poisson(share)
    t = np.where(n > 0, pred[sh, 0] + rng.normal(0.0, 1e-9, sh.size), np.nan)
    lay = Layout(names, 1, False)
    prob = Problem([w], sys0, lay, 1e-9)
    prob.cells[0] = Cells(sh, cols, np.zeros_like(cols), t, np.full(sh.size, 1e3), 60e-9,
                          shots, float(np.median(pred[shots, 3])))
    x0 = lay.pack({"theta0": sys0.scanner.theta0, "tdc_offset": 0.0}, wall)
    st = FitState()
    x = newton(prob, x0, st).x
    assert st.converged
    return prob, x


def test_newton_start_is_the_score_tests_step_and_nears_the_fit(monkeypatch):
    prob, x = _drawn(5)
    # undamped, the block's step measured in its conditional information is the score
    # test's LM (the statistic g_bᵀ [I⁻¹]_bb g_b of hardware_fit.score_tests)
    monkeypatch.setattr(fm, "NEWTON_DAMPING", 0.0)
    st = fm.newton_start(prob, x, H3)
    assert st is not None and st.shrink in fm.NEWTON_SHRINK and st.gain > 0.0
    p2, x2 = extended_problem(prob, x, H3)
    _, g, H = p2.score(x2)
    sc = p2.layout.scales
    bi = [p2.layout.names.index(n) for n in H3]
    Ci = np.linalg.inv(H * sc[:, None] * sc[None, :])[np.ix_(bi, bi)]
    d = np.array([st.block[n] for n in H3]) / sc[bi] / st.shrink  # the block was at 0
    lm = score_tests(prob, x, {"harmonic 3": candidate_blocks((3,))["harmonic 3"]})[0].lm
    assert float(d @ np.linalg.solve(Ci, d)) == pytest.approx(lm, rel=1e-6)
    # the (damped) Newton start lands near the fit with the block free, far nearer than 0
    monkeypatch.undo()
    st = fm.newton_start(prob, x, H3)
    values, walls = prob.layout.unpack(st.x)
    xs = p2.layout.pack({**values, **st.block}, walls)
    fs = FitState()
    best = newton(p2, xs, fs).x
    assert fs.converged
    sd = np.sqrt(np.diag(np.linalg.inv(p2.score(best)[2])))[bi]
    fitted = best[bi]
    start = np.array([st.block[n] for n in H3])
    # (at less than half of 0's distance in σ)
    assert np.all(np.abs(fitted) > 5.0 * sd)  # 0 is many σ away
    far = np.linalg.norm(fitted / sd)
    assert np.linalg.norm((start - fitted) / sd) < 0.5 * far, (start, fitted, sd)
    # the fitted harmonic is the drawn one within 4σ
    assert np.all(np.abs(fitted - np.array(TRUE_H3)) < 4.0 * sd), (fitted, sd)


def test_newton_start_falls_back_to_zero_when_no_step_raises_the_likelihood(monkeypatch):
    prob, x = _drawn(6)
    # a likelihood that every trial step lowers: no start (the block starts at 0)
    real = Problem.loglik
    monkeypatch.setattr(Problem, "loglik", lambda self, z: real(self, z) - 1e9)
    assert fm.newton_start(prob, x, H3) is None
    monkeypatch.undo()
    # and the refit then starts from the fitted point with the block at its nominal 0
    from mems_stereo.calib.result import CalibrationFailure

    refused = CalibrationFailure("implausible result: ...", details={"checks": []})
    stuck = CalibrationFailure("the fit did not converge (no convergence in 100 iterations)")
    seen, outcome = [], {"r": refused}

    def fake_refit(p, z, names, extra, fit_kwargs, start_values=None):
        seen.append((z, start_values))
        return outcome["r"]

    monkeypatch.setattr(fm, "_refit_at", fake_refit)
    monkeypatch.setattr(fm, "newton_start", lambda *a: None)
    assert fm._fit_block(prob, x, list(prob.layout.names), H3, {}) is refused
    assert len(seen) == 1 and seen[0][0] is x and seen[0][1] is None
    # with a start, the refit begins at its point and block values; a fit that reaches
    # its checks (here refused by them) is kept
    st = fm.BlockStart(x + 1.0, {H3[0]: 1e-3, H3[1]: 2e-3}, 5.0, 0.5)
    monkeypatch.setattr(fm, "newton_start", lambda *a: st)
    seen.clear()
    assert fm._fit_block(prob, x, list(prob.layout.names), H3, {}) is refused
    assert len(seen) == 1 and seen[0][0] is st.x and seen[0][1] == st.block
    # one that does not converge from the Newton start is fitted again from 0
    seen.clear()
    outcome["r"] = stuck
    fm._fit_block(prob, x, list(prob.layout.names), H3, {})
    assert [(z is st.x, v) for z, v in seen] == [(True, st.block), (False, None)]
    assert seen[1][0] is x
    # switched off (the benchmarks' baseline): at 0 whatever the step
    monkeypatch.setattr(fm, "NEWTON_START", False)
    seen.clear()
    fm._fit_block(prob, x, list(prob.layout.names), H3, {})
    assert len(seen) == 1 and seen[0][0] is x and seen[0][1] is None


def test_newton_start_without_a_harmonic_stays_near_zero():
    """On a wall drawn without the harmonic, the step is the noise's: within a few σ
    of 0 (the start does not invent a term)."""
    prob, x = _drawn(7, harmonic=(0.0, 0.0))
    st = fm.newton_start(prob, x, H3)
    p2, x2 = extended_problem(prob, x, H3)
    sc = p2.layout.scales
    bi = [p2.layout.names.index(n) for n in H3]
    sd = np.sqrt(np.diag(np.linalg.inv(p2.score(x2)[2])))[bi]
    assert st is not None  # a noise step still raises the likelihood a little
    assert np.all(np.abs([st.block[n] for n in H3]) < 4.0 * sd), (st.block, sd, sc[bi])


def test_rescue_tests_a_fit_that_did_not_converge_at_its_values(monkeypatch):
    """A failure with fitted values (a fit that did not converge has no ``checks``)
    goes to the forward selection at its values; one without values (no wall fitted)
    is returned as it is, untouched."""
    from mems_stereo.calib import goodness
    from mems_stereo.calib.result import CalibrationFailure

    prob, x = _drawn(8)
    calls = []

    def at_values(failure, walls, nominal, priors, jitter):
        calls.append(failure.details["values"])
        return prob, x

    monkeypatch.setattr(goodness, "failed_problem", at_values)
    vals, walls = prob.layout.unpack(x)
    stuck = CalibrationFailure("the fit did not converge (no convergence in 100 iterations)",
                               details={"values": vals, "walls": walls.tolist()})
    tried = []
    monkeypatch.setattr(fm, "_add_block",
                        lambda step, point, chosen, *a: tried.append(chosen))
    # no round passes: rescue's last try (tests/test_joint_rescue.py) finds nothing either
    monkeypatch.setattr(fm, "joint_fit", lambda *a, **k: None)
    out = fm.rescue(stuck, prob.walls, prob.system, [], orders=(3,))
    assert out is stuck and calls == [vals]
    assert tried == [H3]  # the drawn third harmonic is selected and fitted
    nothing = CalibrationFailure("no recording shows a usable wall return", "input")
    assert fm.rescue(nothing, prob.walls, prob.system, []) is nothing and len(calls) == 1
