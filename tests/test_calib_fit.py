"""Calibration on simulated flat-wall recordings: recovery with honest σ, and the
failure modes that must end in a CalibrationFailure (falsy, no system)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mems_stereo.calib import CalibrationFailure, calibrate_scanner_camera, fit_walls
from mems_stereo.calib.association import wall_data
from mems_stereo.calib.family import Case, Wall, simulate_case

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import burkard2022

OFFSETS = {"theta0": 6e-3, "baseline_x": 4e-3, "baseline_z": -3e-3, "tdc_offset": 1.5e-9,
           "theta_mech_max_rel": 0.005, "phase_offset": 0.01}


def _case(walls, seed, offsets=OFFSETS):
    ws = [Wall(d, math.radians(yaw), math.radians(pitch), 0.5, flux, shots, bg)
          for d, yaw, pitch, flux, shots, bg in walls]
    return Case(ws, dict(offsets), seed, [w.distance for w in ws])


# one pytest-xdist worker runs this module: its module fixtures (the good walls and their
# free fit) are computed once (tests/conftest.py: XDIST_GROUPS)

GOOD = [(1.2, 8, 3, 1.0, 1500, 2e5), (2.5, -10, -2, 0.5, 1500, 2e5), (4.0, 5, 0, 0.8, 1500, 2e5)]


@pytest.fixture(scope="module")
def nominal():
    return burkard2022()


@pytest.fixture(scope="module")
def good(nominal):
    case = _case(GOOD, 7)
    walls = [wall_data(r) for r in simulate_case(case, nominal)]
    return case, walls


@pytest.fixture(scope="module")
def free_fit(nominal, good):
    """``fit_walls`` of the good walls without distance priors (two tests read it)."""
    return fit_walls(good[1], nominal)


def _check_within(res, true, k=4.0):
    for n in res.names:
        err = res.values[n] - true.get_param(n)
        assert abs(err) < k * res.std[n], (n, err, res.std[n])


def test_recovers_system_far_from_nominal_within_4_sigma(nominal, good, free_fit):
    """θ0 6 mrad, baseline 4 mm, offset 1.5 ns from the nominal system: the start
    is searched, not taken from the nominal values."""
    case, walls = good
    res = free_fit
    assert res, getattr(res, "reason", "")
    true = case.true_system(nominal)
    _check_within(res, true)
    assert abs(res.values["theta0"] - true.get_param("theta0")) < 1e-3
    assert "baseline_y" in res.unobservable and "baseline_y" not in res.names
    cal = res.system.calibration
    assert cal["converged"] and set(cal["parameters"]) == set(res.names)
    assert len(res.targets) == 3 and res.covariance.shape == (len(res.names),) * 2


def test_measured_distances_sharpen_and_agree(nominal, good, free_fit):
    case, walls = good
    free = free_fit
    priors = [(j, "axis", d, 2e-3) for j, d in enumerate(case.measured)]
    res = fit_walls(walls, nominal, priors=priors)
    assert res
    _check_within(res, case.true_system(nominal))
    assert res.std["baseline_x"] < free.std["baseline_x"]
    for t, d in zip(res.targets, case.measured):
        assert abs(t["distance_axis"] - d) < 3 * math.hypot(2e-3, t["distance_axis_std"])


def test_contradicting_distance_is_named_and_fails(nominal, good):
    case, walls = good
    bad = list(case.measured)
    bad[1] += 0.15
    res = fit_walls(walls, nominal, priors=[(j, "axis", d, 2e-3) for j, d in enumerate(bad)])
    assert not res and isinstance(res, CalibrationFailure)
    assert "measured distance of wall 1" in res.reason
    assert any("wall 1" in w and "contradicts" in w for w in res.warnings)
    with pytest.raises(AttributeError, match="no system"):
        res.system  # noqa: B018


def test_diverging_start_is_not_written(nominal, good):
    """A start far outside the basin (θ0 +60 mrad, baseline +40 mm): the fit either
    finds the truth (within 4σ) or fails; it never returns a confident wrong system."""
    case, walls = good
    true = case.true_system(nominal)
    vals = {n: true.get_param(n) for n in ("theta0", "theta_mech_max", "phase_offset",
                                           "tdc_offset", "baseline_x", "baseline_z")}
    vals["theta0"] += 0.06
    vals["baseline_x"] += 0.04
    start = np.array([[0.0, 0.0, 2.0, 0.0, math.log(0.3)]] * 3)
    res = fit_walls(walls, nominal, initial=(vals, start))
    if res:
        _check_within(res, true)
    else:
        assert res.reason


def test_walls_at_one_distance_are_refused(nominal):
    case = _case([(2.0, 8, 0, 1.0, 2500, 1e5), (2.0, -8, 0, 1.0, 2500, 1e5)], 3)
    walls = [wall_data(r) for r in simulate_case(case, nominal)]
    res = fit_walls(walls, nominal)
    if res:  # what is written must be right
        _check_within(res, case.true_system(nominal))
    else:
        assert "not observable" in res.reason and res.kind == "input"


def test_walls_parallel_to_the_baseline_refused(nominal):
    case = _case([(2.0, 0, 0, 1.0, 2500, 1e5), (2.0, 0, 5, 1.0, 2500, 1e5)], 4)
    walls = [wall_data(r) for r in simulate_case(case, nominal)]
    res = fit_walls(walls, nominal)
    assert not res
    assert "not observable" in res.reason


def test_no_return_is_an_input_failure(nominal, monkeypatch):
    """One fit: ``fit_walls(walls, nominal)`` as calibrate_scanner_camera →
    calibrate_system calls it (recorded by a spy) fails as an input failure, and the
    calib3d-shaped wrapper raises NotObservableError with its reason."""
    import mems_stereo.calib.calibrate as calib_mod

    case = _case([(2.0, 5, 0, 0.001, 800, 3e6)], 5)
    seen = []

    def spy(walls, system, **kw):
        seen.append((walls, kw, fit_walls(walls, system, **kw)))
        return seen[-1][2]

    monkeypatch.setattr(calib_mod, "fit_walls", spy)
    with pytest.raises(NotObservableError) as e:
        calibrate_scanner_camera(simulate_case(case, nominal), nominal)
    ((walls, kw, res),) = seen
    # the call as made directly: one wall, no priors, nothing fixed, the default free set
    assert len(walls) == 1 and not kw.get("priors") and not kw.get("fix")
    assert kw.get("free") is None
    assert not res and res.kind == "input" and "usable wall return" in res.reason
    assert res.reason in str(e.value)


def test_calib3d_shaped_api(nominal):
    case = _case(GOOD, 7)
    recs = simulate_case(case, nominal)
    cal = calibrate_scanner_camera(recs, nominal, target_distances=case.measured,
                                   distance_std=2e-3)
    rms, system, std, per_target = cal.rms, cal.system, cal.std, cal.targets
    assert set(rms) == {"pixel", "time"} and 0 < rms["pixel"] < 1.5
    assert abs(system.scanner.theta0 - case.true_system(nominal).scanner.theta0) < 4 * std["theta0"]
    assert len(per_target) == 3 and "distance_axis" in per_target[0]


@pytest.mark.stress  # 12-17 s: with the stress runs (pytest -m stress)
def test_collapsed_spot_is_not_written_with_an_overconfident_sigma(nominal):
    """A family draw at 1/8 of its shots where, from the track-search start, one
    wall's fitted spot σ collapses onto its lower bound, which inflates the pixel
    information (an overconfident σ).  The spot is reset and refitted; the
    written system lies within 4σ of the truth and no wall's spot sits at the bound."""
    from mems_stereo.calib.family import draw_case
    from mems_stereo.calib.problem import SPOT_MIN

    case = draw_case(np.random.default_rng(1005), 1005)
    walls = [wall_data(r) for r in simulate_case(case, nominal, shot_scale=8)]
    res = fit_walls(walls, nominal)
    if res:
        _check_within(res, case.true_system(nominal))
        assert all(t["spot_px"] > 1.05 * SPOT_MIN for t in res.targets)
    else:
        assert res.reason


def test_consistency_needs_a_large_and_significant_shift():
    """A quarter's shift counts only when it is large (beyond 1 ns and half the pulse σ,
    or 0.3 px) and significant on its own (> SHIFT_Z σ)."""
    from mems_stereo.calib import observability as obs

    sig = 6.3e-9
    z4 = np.zeros(4)

    def big(dt, du, z):
        return obs.big_shift(np.asarray(dt, float), np.asarray(du, float), np.asarray(z, float),
                             sig)

    # a weak wall's lightly lit quarter: 10 ns, but only 7σ
    assert not big([0, 0, 0, -10e-9], z4, [0, 0, 0, -7.3, 0, 0, 0, 0])
    # a piled-up wall: 2.2 ns at 9.5σ, within half the pulse σ
    assert not big([0, 0, 0, 2.2e-9], z4, [0, 0, 0, 9.5, 0, 0, 0, 0])
    # a real step in depth: 5 ns at 30σ, or a column shift of 0.6 px at 20σ
    assert big([0, 5e-9, 0, 0], z4, [0, 30, 0, 0, 0, 0, 0, 0])
    assert big(z4, [0, 0, 0.6, 0], [0, 0, 0, 0, 0, 0, 20, 0])
    # significant but tiny shifts are the model's precision, not a failure
    assert not big([0.5e-9, 0, 0, 0], [0.1, 0, 0, 0], [50, 0, 0, 0, 50, 0, 0, 0])


def test_expected_information_agrees_with_the_outer_product(nominal, good):
    """The expected information (:mod:`mems_stereo.calib.expected_info`, used by the
    flat-wall consistency test) and the outer product of the observed scores (the
    solver's) at the true system and walls: the same σ of every system parameter
    within 15 % (the simulator and the first-photon model agree)."""
    from mems_stereo.calib import observability as obs
    from mems_stereo.calib.expected_info import expected_information
    from mems_stereo.calib.problem import Layout, Problem
    from mems_stereo.calib.solver import build_cells

    from mems_stereo.physics.pulse import pulse_sigma

    case, walls = good
    true = case.true_system(nominal)
    names = ["theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x",
             "baseline_z"]
    wp = np.zeros((len(walls), 5))
    for j, w in enumerate(case.walls):  # the walls' traces in the scan plane y = 0
        n = w.normal
        k = math.hypot(n[0], n[2])
        wp[j] = [math.atan2(-n[0], -n[2]), 0.0, -n[2] * w.distance / k, math.log(w.flux),
                 math.log(0.3)]
    lay = Layout(names, len(walls), False)
    prob = Problem(walls, nominal, lay, pulse_sigma(nominal.laser.pulse_fwhm, 50e-12))
    x = build_cells(prob, lay.pack({n: true.get_param(n) for n in names}, wp), radius=2)
    sd = []
    for H in (prob.score(x)[2], expected_information(prob, x)):
        cov = obs.covariance(H, lay.scales)[0]
        sd.append(np.sqrt(np.diag(cov))[:len(names)])
    ratio = sd[0] / sd[1]
    assert np.all(np.abs(ratio - 1) < 0.15), dict(zip(names, ratio))
