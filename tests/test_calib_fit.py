"""Calibration fit on synthetic flat-target detections: recovery, σ, degenerate cases."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from mems_stereo.calib.fit import ObservabilityWarning, fit_detections
from mems_stereo.calib.synth import synthetic_target

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import burkard2022

TARGETS = [(0.05, 1.2, 3.0), (-0.1, 2.0, 1.5), (0.02, 3.5, 0.6)]  # tilt rad, distance m, μ


@pytest.fixture(scope="module")
def nominal():
    return burkard2022()


@pytest.fixture(scope="module")
def true_system(nominal):
    return nominal.with_params(theta0=nominal.scanner.theta0 + 2e-3, baseline_x=-0.122,
                               baseline_z=-0.002, tdc_offset=1.5e-9, phase_offset=5e-3)


def _targets(true_system, n_shots, seed, spec=TARGETS):
    rng = np.random.default_rng(seed)
    return [synthetic_target(true_system, a, d, n_shots, rng, mu=m, lam=1e5,
                             source=f"{d} m") for a, d, m in spec]


@pytest.fixture(scope="module")
def fitted(nominal, true_system):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fit_detections(_targets(true_system, 800, 3), nominal)
    return res, caught


def test_recovers_parameters_within_3_sigma(fitted, true_system):
    res, _ = fitted
    assert res.converged
    for name in res.names:
        err = res.values[name] - true_system.get_param(name)
        assert abs(err) < 3 * res.std[name], (name, err, res.std[name])


def test_baseline_y_found_unobservable_by_jacobian(fitted):
    res, caught = fitted
    assert "baseline_y" in res.unobservable and "baseline_y" not in res.names
    msgs = [str(w.message) for w in caught if issubclass(w.category, ObservabilityWarning)]
    assert any("baseline_y" in m for m in msgs)
    cal = res.system.calibration
    assert cal["unobservable"] == ["baseline_y"]
    assert set(cal["parameters"]) == set(res.names)
    assert cal["rms_pixel"] == pytest.approx(res.rms_pixel)


@pytest.mark.slow
def test_sigma_matches_scatter_of_repeated_fits(nominal, true_system, fitted):
    """Propagated σ of θ0 vs the spread of estimates over independent data sets."""
    res, _ = fitted
    est = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in (11, 12, 13):
            r = fit_detections(_targets(true_system, 800, seed), nominal)
            est.append(r.values["theta0"])
    spread = np.std(est, ddof=1)
    # 3 samples: the sample σ lies within a factor 3 of the true σ with high probability
    assert res.std["theta0"] / 3 < spread < 3 * res.std["theta0"]


def test_single_distance_not_observable(nominal, true_system):
    tg = _targets(true_system, 800, 5, spec=[(0.08, 2.0, 1.0)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ObservabilityWarning)
        with pytest.raises(NotObservableError, match="tdc_offset|baseline_x|baseline_z"):
            fit_detections(tg, nominal)


def test_single_distance_known_distance_or_warn(nominal, true_system):
    tg = _targets(true_system, 800, 5, spec=[(0.08, 2.0, 1.0)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fit_detections(tg, nominal, on_unobservable="warn")
    assert set(res.unobservable) - {"baseline_y"}
    assert any("trades off" in str(w.message) for w in caught)


def test_target_parallel_to_baseline_single_pose(nominal, true_system):
    """A wall facing the sensor (parallel to the baseline) at one distance: error, no number."""
    tg = _targets(true_system, 800, 8, spec=[(0.0, 2.0, 1.0)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(NotObservableError) as e:
            fit_detections(tg, nominal)
    assert any(n in str(e.value) for n in ("baseline_x", "tdc_offset", "target 0"))


def test_too_few_detections(nominal, true_system):
    tg = _targets(true_system, 800, 6)
    tg[1] = synthetic_target(true_system, -0.1, 2.0, 20, np.random.default_rng(1), mu=0.5)
    with pytest.raises(NotObservableError, match="too few signal detections in target 1"):
        fit_detections(tg, nominal)


def test_far_start_converges_or_says_so(nominal, true_system):
    tg = _targets(true_system, 800, 9)
    start = {"baseline_x": -0.135, "theta0": nominal.scanner.theta0 - 0.02}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit_detections(tg, nominal, initial_values=start)
    if res.converged:
        for name in res.names:
            err = res.values[name] - true_system.get_param(name)
            assert abs(err) < 4 * res.std[name], (name, err)
    else:
        assert "did not converge" in res.message


def test_known_distances_break_tradeoff(nominal, true_system, fitted):
    res, _ = fitted
    tg = _targets(true_system, 800, 3)
    # measured along the optical axis (the default): the plane n(α)·x = D meets
    # the z axis at z = D / cos α
    d_axis = [d / np.cos(a) for a, d, _ in TARGETS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r2 = fit_detections(tg, nominal, known_distances=d_axis)
    assert r2.std["tdc_offset"] < 0.5 * res.std["tdc_offset"]
    assert r2.std["baseline_x"] < 0.5 * res.std["baseline_x"]
    for name in r2.names:
        err = r2.values[name] - true_system.get_param(name)
        assert abs(err) < 3 * r2.std[name], (name, err, r2.std[name])
    # the fit's own optical-axis distances agree with the measured ones
    np.testing.assert_allclose(r2.extra["axis_distance"], d_axis, atol=3e-3)


def test_axis_and_normal_distance_kinds_agree(nominal, true_system):
    """The same known geometry given as optical-axis or as perpendicular distances
    gives the same fit; an axis distance given as a perpendicular one (wrong by
    D·(1/cos α − 1), 10 mm at α = −0.1) pulls the estimates."""
    tg = _targets(true_system, 800, 3)
    d_axis = [d / np.cos(a) for a, d, _ in TARGETS]
    d_norm = [d for _, d, _ in TARGETS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ra = fit_detections(tg, nominal, known_distances=d_axis, distance_std=5e-4)
        rn = fit_detections(tg, nominal, known_distances=d_norm, distance_std=5e-4,
                            distance_kind="normal")
        rw = fit_detections(tg, nominal, known_distances=d_axis, distance_std=5e-4,
                            distance_kind="normal")
    for name in ra.names:  # different functions of (α, D) are pinned: close, not equal
        tv = true_system.get_param(name)
        assert abs(ra.values[name] - tv) < 3 * ra.std[name], name
        assert abs(rn.values[name] - tv) < 3 * rn.std[name], name
        assert abs(ra.values[name] - rn.values[name]) < ra.std[name], name
    z = (rw.values["baseline_x"] - true_system.get_param("baseline_x")) / rw.std["baseline_x"]
    assert abs(z) > 3, z
