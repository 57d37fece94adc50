"""A refused hardware-term fit tried again from a new start search, and rescue's
last try (calib/full_model: ``_add_block``'s retry, :func:`joint_fit`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from mems_stereo.calib import full_model as fm
from mems_stereo.calib import goodness
from mems_stereo.calib.hardware_fit import TAIL_DECAYS
from mems_stereo.calib.model import PULSE_PARAMS
from mems_stereo.calib.result import CalibrationFailure
from mems_stereo.calib.solver import FitState, newton
from test_hardware_fit import _synthetic_problem
from test_newton_start import H3, _drawn


def _passing(names):
    """A stand-in for a result that passes its checks."""
    return SimpleNamespace(names=list(names), unobservable=[], warnings=[], extra={})


def _refused(prob, x):
    vals, walls = prob.layout.unpack(x)
    return CalibrationFailure("implausible result: wall 0 (w) is not a flat wall",
                              details={"values": vals, "walls": walls.tolist(), "checks": {}})


@pytest.fixture(scope="module")
def drawn():
    return _drawn(8)


def test_a_refused_block_fit_is_fitted_again_from_a_new_start_search(monkeypatch, drawn):
    prob, x = drawn
    names = list(prob.layout.names)
    local = _refused(prob, x)
    monkeypatch.setattr(fm, "_fit_block", lambda *a, **k: local)
    calls, answer = [], {}

    def fake_fit_walls(walls, system, **kw):
        calls.append((walls, system, kw))
        return answer["r"]

    monkeypatch.setattr(fm, "fit_walls", fake_fit_walls)
    answer["r"] = _passing(names + H3)
    step = fm._Step(None, [], None, [], good="before")
    nxt = fm._add_block(step, (prob, x, names), H3, {"jitter": 5e-11}, set())
    # the walls, nominal system and measured distances of the refused fit's problem,
    # every parameter free at once, from the global start search (no start values)
    assert len(calls) == 1
    walls, system, kw = calls[0]
    assert walls is prob.walls and system is prob.system and kw["priors"] is prob.priors
    assert kw["free"] == names + H3 and "initial" not in kw and kw["jitter"] == 5e-11
    assert nxt.fit is answer["r"] and nxt.good is answer["r"]
    # refused from the new start too: the local fit is kept and tested on
    answer["r"] = _refused(prob, x)
    nxt = fm._add_block(step, (prob, x, names), H3, {}, set())
    assert nxt.fit is local and nxt.good == "before" and len(calls) == 2
    # switched off: no new start search
    monkeypatch.setattr(fm, "GLOBAL_RETRY", False)
    assert fm._add_block(step, (prob, x, names), H3, {}, set()).fit is local
    assert len(calls) == 2


def test_rescue_fits_the_significant_blocks_at_once_when_no_round_passes(monkeypatch, drawn):
    prob, x = drawn
    names = list(prob.layout.names)
    failure = _refused(prob, x)
    monkeypatch.setattr(goodness, "failed_problem", lambda *a: (prob, x))
    monkeypatch.setattr(fm, "_add_block", lambda *a, **k: None)  # every round fails
    seen = []

    def fake_fit_walls(walls, system, **kw):
        seen.append(kw["free"])
        return _passing(kw["free"])

    monkeypatch.setattr(fm, "fit_walls", fake_fit_walls)
    out = fm.rescue(failure, prob.walls, prob.system, [], orders=(3,))
    # the drawn third harmonic is significant at the failure's point: fitted with the
    # failure's parameters from a new start search, and the result says so
    assert len(seen) == 1 and seen[0][:len(names)] == names and set(H3) <= set(seen[0])
    assert out is not failure and list(out.names) == seen[0]
    assert "harmonic3_cos, harmonic3_sin" in out.warnings[0]
    assert "the ideal model's fit was refused" in out.warnings[0]
    # nothing significant (a wall drawn without the harmonic): the failure stays
    prob0, x0 = _drawn(7, harmonic=(0.0, 0.0))
    monkeypatch.setattr(goodness, "failed_problem", lambda *a: (prob0, x0))
    seen.clear()
    assert fm.rescue(_refused(prob0, x0), prob0.walls, prob0.system, [], orders=(3,)) \
        is not None and seen == []


def test_joint_fit_adds_the_pulse_tail_where_its_score_test_selects_one(monkeypatch, drawn):
    prob, x = drawn
    tp, tx = _synthetic_problem(np.random.default_rng(4), tail=(0.3, 2e-9))
    tx = newton(tp, tx, FitState()).x  # the ideal model's fit of a wall with a tail
    points = iter([(prob, x), (tp, tx)])
    monkeypatch.setattr(goodness, "failed_problem", lambda *a: next(points))
    monkeypatch.setattr(fm, "fit_walls", lambda *a, **k: _refused(prob, x))
    got = []

    def fake_refit(p, z, names, extra, fit_kwargs, start_values=None):
        got.append((p, z, list(extra), dict(start_values)))
        return _passing(list(names) + list(extra))

    monkeypatch.setattr(fm, "_refit_at", fake_refit)
    monkeypatch.setattr(fm, "newton_start", lambda *a: pytest.fail("no block to start"))
    step = fm._Step(_refused(prob, x), [], prob.system, [])
    r = fm.joint_fit(step, {"harmonic 3": tuple(H3)}, {})
    test = r.extra["tail_test"]
    assert test.selected and test.name == "pulse tail" and test.p_value < 1e-3
    # at the refused joint fit's point: the tail from share 0.1 at the test's decay,
    # tdc_offset less the mean delay w·τ (the core's peak)
    (p, z, extra, start), = got
    assert p is tp and z is tx and extra == list(PULSE_PARAMS)
    t0 = tp.layout.unpack(tx)[0]["tdc_offset"]
    decay = start[PULSE_PARAMS[1]]
    assert decay in TAIL_DECAYS  # the decay of the most significant test
    assert start == pytest.approx({PULSE_PARAMS[0]: fm.JOINT_TAIL_SHARE,
                                   PULSE_PARAMS[1]: decay,
                                   "tdc_offset": t0 - fm.JOINT_TAIL_SHARE * decay})
    # a wall without a tail: no tail is started (and none is fitted)
    assert fm._tail_start(prob, x, list(prob.layout.names))[0] is None
