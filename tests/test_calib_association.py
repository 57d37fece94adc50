"""The track search of the initialisation on weak walls (a wall the association
misses makes a calibration fail)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mems_stereo.calib.association import wall_data
from mems_stereo.calib.family import Case, Wall, simulate_case
from mems_stereo.calib.problem import shot_model
from mems_stereo.calib.track import MIN_TRACK_POINTS, find_track, track_from_pose
from mems_stereo.calib.wall_search import poisson_z
from scipy.stats import norm, poisson

from mems_stereo.errors import NotObservableError
from mems_stereo.model.system import burkard2022
from mems_stereo.physics.pulse import pulse_sigma


@pytest.fixture(scope="module")
def nominal():
    return burkard2022()


def test_poisson_significance_matches_the_exact_tail():
    """A few counts over a tiny background are significant ((n − e)/√(e + 1) said
    they were not); large counts agree with the Gaussian limit."""
    for n, e in [(3, 0.003), (4, 0.003), (6, 0.5), (30, 10.0), (1200, 1000.0)]:
        exact = norm.isf(poisson.sf(n - 1, e))
        assert abs(float(poisson_z(n, e)) - exact) < 0.25 * exact + 0.3, (n, e, exact)
    assert float(poisson_z(4, 0.003)) > 6.0 > 4.0 / math.sqrt(1.003)
    assert float(poisson_z(0, 2.0)) < 0 and float(poisson_z(2.0, 2.0)) == 0.0


@pytest.mark.parametrize("flux,shots,bg", [(0.05, 4000, 1e4), (0.3, 800, 5e4)])
def test_weak_wall_at_low_background_is_followed(nominal, flux, shots, bg):
    """~200–240 signal photons over the whole scan, spread over 8–128 phase bins:
    too few per bin for 3-column boxes; boxes as wide as a phase bin's sweep and
    the Poisson significance follow the track, and the points lie on the true one."""
    offsets = {"theta0": 4e-3, "tdc_offset": 1e-9, "baseline_x": 3e-3}
    case = Case([Wall(0.8, math.radians(8), 0.0, 0.5, flux, shots, bg)], offsets, 11, [0.8])
    w = wall_data(simulate_case(case, nominal)[0])
    tr = find_track(w, pulse_sigma(nominal.laser.pulse_fwhm, 50e-12))
    assert tr.u.size >= MIN_TRACK_POINTS
    true = case.true_system(nominal)
    wall = case.walls[0]
    n = wall.normal
    alpha = math.atan2(-n[0], -n[2])
    D = -n[2] * wall.distance / math.hypot(n[0], n[2])
    vals = {k: true.get_param(k) for k in ("theta0", "theta_mech_max", "phase_offset",
                                           "tdc_offset", "baseline_x", "baseline_z")}
    pred, ok = shot_model(true, vals, np.array([alpha, 0.0, D, 0.0, 0.0]), tr.phase)
    assert ok.all()
    # a point is the mean column of a phase bin's return: within the bin's sweep,
    # and its stated column σ covers its error (the fit's on-track check uses it)
    assert np.median(np.abs(pred[:, 1] - tr.u)) < 3.0
    assert tr.u_err.shape == tr.u.shape and np.all(tr.u_err >= 0.5)
    assert np.mean(np.abs(pred[:, 1] - tr.u) < 3.0 * tr.u_err) >= 0.75


def test_background_alone_gives_no_track(nominal):
    case = Case([Wall(0.8, 0.1, 0.0, 0.5, 1e-5, 4000, 1e4)], {"theta0": 0.0}, 12, [0.8])
    w = wall_data(simulate_case(case, nominal)[0])
    try:
        tr = find_track(w, pulse_sigma(nominal.laser.pulse_fwhm, 50e-12))
    except NotObservableError:
        return
    assert tr.u.size < MIN_TRACK_POINTS


@pytest.mark.stress  # 12-17 s: with the stress runs (pytest -m stress)
def test_walls_the_track_search_misses_are_found_by_the_pose_search(nominal):
    """One bright wall and two faint ones (0.05 and 0.08 photons per shot at 0.5–1
    MHz): the track search follows only the bright one, whose fit alone is
    degenerate; the pose search over the whole recordings, with the system of that
    fit (offset and baseline pinned at nominal where it does not determine them),
    finds the other two, and the joint fit is right within 4σ."""
    offsets = {"theta0": 6e-3, "baseline_x": 4e-3, "baseline_z": -3e-3, "tdc_offset": 1.5e-9,
               "theta_mech_max_rel": 0.005, "phase_offset": 0.01}
    spec = [(1.0, 8, 2.0, 1500, 2e5), (2.5, -10, 0.05, 3000, 5e5), (4.0, 5, 0.08, 3000, 1e6)]
    ws = [Wall(d, math.radians(y), 0.0, 0.5, f, n, bg) for d, y, f, n, bg in spec]
    case = Case(ws, offsets, 5, [w.distance for w in ws])
    walls = [wall_data(r) for r in simulate_case(case, nominal)]
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, 50e-12)
    tracked = 0
    for w in walls:
        try:
            tracked += find_track(w, sigma).u.size >= MIN_TRACK_POINTS
        except NotObservableError:
            pass
    assert tracked == 1
    from mems_stereo.calib.fit import fit_walls

    res = fit_walls(walls, nominal)
    assert res, res.reason
    assert len(res.targets) == 3 and not any(w.startswith("left out") for w in res.warnings)
    true = case.true_system(nominal)
    for n in res.names:
        assert abs(res.values[n] - true.get_param(n)) < 4 * res.std[n], n


@pytest.mark.slow
def test_a_wall_too_weak_for_any_phase_bin_gets_its_track_from_the_pose_search(nominal):
    """A family draw where no wall of three has a track, although the data determine
    the system: 0.05 photons per shot over
    2,500 shots is one significant phase bin at most; the pose search over the
    whole recording with the *nominal* system (the truth 9 mrad, 9 mm and 2.5 ns
    away) finds it, and the columns measured around its image lie on the true
    track within their stated σ.  Background alone gives no track."""
    offsets = {"theta0": -9e-3, "tdc_offset": 2.5e-9, "baseline_x": 9e-3, "baseline_z": -6e-3}
    case = Case([Wall(0.7, math.radians(-6), 0.0, 0.5, 0.05, 2500, 3e4)], offsets, 7, [0.7])
    w = wall_data(simulate_case(case, nominal)[0])
    sigma = pulse_sigma(nominal.laser.pulse_fwhm, 50e-12)
    try:
        assert find_track(w, sigma).u.size < MIN_TRACK_POINTS
    except NotObservableError:
        pass
    tr = track_from_pose(w, nominal, sigma)
    assert tr is not None and tr.u.size >= MIN_TRACK_POINTS
    true = case.true_system(nominal)
    n = case.walls[0].normal
    alpha = math.atan2(-n[0], -n[2])
    D = -n[2] * case.walls[0].distance / math.hypot(n[0], n[2])
    vals = {k: true.get_param(k) for k in ("theta0", "theta_mech_max", "phase_offset",
                                           "tdc_offset", "baseline_x", "baseline_z")}
    pred, ok = shot_model(true, vals, np.array([alpha, 0.0, D, 0.0, 0.0]), tr.phase)
    assert ok.all()
    err = pred[:, 1] - tr.u
    assert np.median(np.abs(err)) < 1.5
    assert np.mean(np.abs(err) < 3.0 * tr.u_err) >= 0.75
    bg = Case([Wall(0.8, 0.1, 0.0, 0.5, 1e-5, 4000, 1e5)], {"theta0": 0.0}, 12, [0.8])
    assert track_from_pose(wall_data(simulate_case(bg, nominal)[0]), nominal, sigma) is None
