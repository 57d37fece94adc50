"""The two-axis system description, the gimbal reflection model and angle recovery."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mems_stereo.errors import FormatError
from mems_stereo.model.presets import lissajous64, raster128x96
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.scanner2d import (
    Axis2Monitor,
    fast_axis,
    is_two_axis,
    mirror_normal_2d,
    scan_angles_2d,
    scan_direction_2d,
    scan_direction_2d_jacobian,
    triangle_wave,
)
from mems_stereo.model.system import (
    load_system,
    system_from_dict,
    system_from_json,
    system_to_dict,
    system_to_json,
)
from mems_stereo.sim.trajectory import Trajectory, monitor_zero_crossings

ROOT = Path(__file__).resolve().parents[1]


def test_version1_files_unchanged_by_the_extension():
    for name in ("nominal_system.json", "calib_true_system.json"):
        raw = json.loads((ROOT / "samples" / name).read_text())
        s = load_system(ROOT / "samples" / name)
        assert s.scanner.axis2 is None and not is_two_axis(s)
        out = system_to_dict(s)
        assert "axis2" not in out["scanner"]
        assert out["scanner"] == {k: v for k, v in raw["scanner"].items()}


@pytest.mark.parametrize("make", [lissajous64, raster128x96])
def test_two_axis_json_round_trip(make):
    s = make()
    t = system_from_json(system_to_json(s))
    a, b = s.scanner.axis2, t.scanner.axis2
    assert b.mode == a.mode and b.gimbal == a.gimbal
    np.testing.assert_array_equal(b.axis, a.axis)
    assert (b.theta0, b.f_mech, b.theta_mech_max) == (a.theta0, a.f_mech, a.theta_mech_max)
    assert system_to_json(t) == system_to_json(s)


@pytest.mark.parametrize("change, field", [
    ({"mode": "galvo"}, "scanner.axis2.mode"),
    ({"axis": [0.0, 1.0, 0.0]}, "scanner.axis2.axis"),  # parallel to a1 = -y
    ({"axis": [0.0, 0.0, 2.0]}, "scanner.axis2.axis"),
    ({"gimbal": "inner"}, "scanner.axis2.gimbal"),
    ({"theta_mech_max": -0.1}, "scanner.axis2.theta_mech_max"),
])
def test_axis2_validation_names_the_field(change, field):
    d = system_to_dict(lissajous64())
    d["scanner"]["axis2"].update(change)
    with pytest.raises(FormatError, match=field.replace(".", r"\.")):
        system_from_dict(d, "x.json")


@pytest.mark.parametrize("gimbal", ["outer2", "outer1"])
def test_zero_second_angle_is_the_one_axis_law(gimbal):
    s = lissajous64()
    sc = replace(s.scanner, axis2=replace(s.scanner.axis2, gimbal=gimbal))
    th = np.linspace(0.5, 1.0, 7)
    np.testing.assert_allclose(scan_direction_2d(th, 0.0, sc), scan_direction(th, sc),
                               atol=1e-15)


@pytest.mark.parametrize("gimbal", ["outer2", "outer1"])
def test_gimbal_normal_against_rotation_matrices(gimbal):
    # independent derivation: scipy rotation vectors, R(a, α) = exp(α [a]x)
    s = lissajous64()
    sc = replace(s.scanner, axis2=replace(s.scanner.axis2, gimbal=gimbal))
    a1, a2 = fast_axis(sc), sc.axis2.axis
    e1 = sc.normal_basis[0]
    rng = np.random.default_rng(5)
    t1 = rng.uniform(0.4, 1.2, 20)
    t2 = rng.uniform(-0.3, 0.3, 20)
    for x1, x2 in zip(t1, t2):
        R1 = Rotation.from_rotvec(x1 * a1).as_matrix()
        R2 = Rotation.from_rotvec(x2 * a2).as_matrix()
        n_ref = (R2 @ R1 @ e1) if gimbal == "outer2" else (R1 @ R2 @ e1)
        np.testing.assert_allclose(mirror_normal_2d(x1, x2, sc), n_ref, atol=1e-14)
        d_ref = (np.eye(3) - 2 * np.outer(n_ref, n_ref)) @ sc.laser_direction  # Householder
        np.testing.assert_allclose(scan_direction_2d(x1, x2, sc), d_ref, atol=1e-14)


def test_gimbal_orders_differ_and_coupling_shifts_theta2():
    s = lissajous64()
    sc2 = s.scanner
    sc1 = replace(sc2, axis2=replace(sc2.axis2, gimbal="outer1"))
    assert np.max(np.abs(scan_direction_2d(0.9, 0.2, sc1) - scan_direction_2d(0.9, 0.2, sc2))) > 1e-3
    k = 0.01
    scc = replace(sc2, axis2=replace(sc2.axis2, coupling=k))
    t1 = sc2.theta0 + 0.1
    np.testing.assert_allclose(scan_direction_2d(t1, 0.05, scc),
                               scan_direction_2d(t1, 0.05 + k * 0.1, sc2), atol=1e-15)


def test_direction_jacobian_against_analytic_derivative():
    sc = lissajous64().scanner
    t1, t2 = 0.8, 0.1
    g1, g2 = scan_direction_2d_jacobian(t1, t2, sc)
    n = mirror_normal_2d(t1, t2, sc)
    l = sc.laser_direction
    dn2 = np.cross(sc.axis2.axis, n)  # outer2: ∂n/∂θ2 = a2 × n
    ref2 = -2 * ((dn2 @ l) * n + (n @ l) * dn2)
    np.testing.assert_allclose(g2, ref2, atol=1e-8)
    dn1 = Rotation.from_rotvec(t2 * sc.axis2.axis).as_matrix() @ (
        -math.sin(t1) * sc.normal_basis[0] + math.cos(t1) * sc.normal_basis[1])
    ref1 = -2 * ((dn1 @ l) * n + (n @ l) * dn1)
    np.testing.assert_allclose(g1, ref1, atol=1e-8)


def test_triangle_wave():
    np.testing.assert_allclose(triangle_wave([0, np.pi / 2, np.pi, 3 * np.pi / 2, 2 * np.pi]),
                               [1, 0, -1, 0, 1], atol=1e-12)


@pytest.mark.parametrize("make", [lissajous64, raster128x96])
def test_angles_of_both_axes_from_the_monitors(make):
    s = make()
    sc, a2 = s.scanner, s.scanner.axis2
    rng = np.random.default_rng(2)
    t = np.arange(4000) / s.laser.f_rep
    tr1 = Trajectory(sc.f_mech, 0.3, 0.0, 0.0, sc.theta0, sc.theta_mech_max, 0.0)
    zc, ri = monitor_zero_crossings(tr1, t, rng, 0.0)
    if a2.mode == "resonant":
        tr2 = Trajectory(a2.f_mech, 1.1, 0.0, 0.0, a2.theta0, a2.theta_mech_max, 0.0)
        z2, r2 = monitor_zero_crossings(tr2, t, rng, 0.0)
        mon = Axis2Monitor(zero_crossings=z2, rising=r2)
        th2_true = tr2.theta(t)
        tol2 = 1e-9
    else:
        pt = np.arange(-1e-3, t[-1] + 1e-3, 1e-5)
        mon = Axis2Monitor(time=pt, position=a2.theta_mech_max * np.sin(2 * np.pi * 20 * pt))
        th2_true = a2.theta0 + a2.theta_mech_max * np.sin(2 * np.pi * 20 * t)
        tol2 = 1e-6  # linear interpolation of a sampled sine
    th1, th2, valid = scan_angles_2d(t, zc, ri, mon, sc)
    assert valid.all()
    np.testing.assert_allclose(th1, tr1.theta(t), atol=1e-9)
    np.testing.assert_allclose(th2, th2_true, atol=tol2)
    # outside the monitor's span: unknown, never extrapolated
    th1, th2, valid = scan_angles_2d(t + 10.0, zc, ri, mon, sc)
    assert not valid.any() and np.all(np.isnan(th2))
