"""MEMS scanner: trajectory, zero-crossing phase recovery, reflection law, θ0."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mems_stereo.errors import FormatError, GeometryError
from mems_stereo.model.scanner import (
    crossing_phases,
    mirror_normal,
    phase_from_zero_crossings,
    reflect,
    scan_angles,
    scan_direction,
    scan_direction_derivative,
    theta0_exact,
    theta0_small_angle,
    theta_mech_samples,
    theta_mech_trajectory,
)

unit = st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))


@given(unit, unit)
def test_reflection_keeps_unit_length_and_is_an_involution(d, n):
    r = reflect(d, n)
    assert np.linalg.norm(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(reflect(r, n), d, atol=1e-12)
    # angle of incidence equals angle of reflection
    assert float(r @ n) == pytest.approx(-float(d @ n), abs=1e-12)


@given(st.floats(-math.pi, math.pi))
def test_scan_direction_closed_form_for_the_paper_geometry(theta):
    from mems_stereo.model.system import burkard2022

    sc = burkard2022().scanner
    d = scan_direction(theta, sc)
    np.testing.assert_allclose(d, [math.cos(2 * theta), 0.0, math.sin(2 * theta)], atol=1e-12)
    # derivative against a central difference
    h = 1e-6
    num = (scan_direction(theta + h, sc) - scan_direction(theta - h, sc)) / (2 * h)
    np.testing.assert_allclose(scan_direction_derivative(theta, sc), num, atol=1e-8)


def test_mirror_normal_rejects_degenerate_basis():
    with pytest.raises(FormatError, match="orthogonal"):
        mirror_normal(0.3, [[1, 0, 0], [0.6, 0.8, 0]])
    with pytest.raises(FormatError, match="unit vector"):
        mirror_normal(0.3, [[1, 0, 0], [0, 0, 0]])
    with pytest.raises(FormatError, match=r"shape \(2, 3\)"):
        mirror_normal(0.3, [[1, 0, 0]])


def test_non_unit_laser_direction_is_rejected(system):
    from dataclasses import replace

    sc = replace(system.scanner, laser_direction=np.array([-2.0, 0, 0]))
    with pytest.raises(GeometryError, match="unit vector"):
        scan_direction(0.7, sc)


@given(st.floats(0.01, 0.5), st.floats(0.5, 50.0))
def test_theta0_exact_crosses_the_optical_axis_at_working_distance(xm0, w):
    """Numerically: the beam at θ0 from the mirror at (−x_M0, 0, 0) meets x = 0 at z = W."""
    from mems_stereo.model.system import burkard2022

    sc = burkard2022().scanner
    d = scan_direction(theta0_exact(xm0, w), sc)
    s = xm0 / d[0]  # path to x = 0
    assert s * d[2] == pytest.approx(w, rel=1e-10)
    # the paper's small-angle form differs at third order in x/W
    diff = abs(theta0_exact(xm0, w) - theta0_small_angle(xm0, w))
    assert diff <= (xm0 / w) ** 3 / 8 + 1e-15


def test_paper_eq1_samples_match_the_trajectory():
    f_mech, f_rep, amp, phi0 = 1570.0, 20000.0, 0.2077, 0.3
    k = np.arange(100)
    np.testing.assert_allclose(theta_mech_samples(100, f_mech / f_rep, amp, phi0),
                               theta_mech_trajectory(k / f_rep, amp, f_mech, phi0), atol=1e-15)


# ---------------------------------------------------------------------------
# zero crossings


def _chirp_crossings(f0, a, phi0, t_end):
    """Zero crossings of cos(φ(t)) with φ = 2π(f0 t + a t²/2) + φ0, solved in closed form."""
    out_t, out_r = [], []
    m = math.ceil((phi0 - math.pi / 2) / math.pi)
    while True:
        target = math.pi / 2 + m * math.pi
        c = (phi0 - target) / (2 * math.pi)  # a/2 t² + f0 t + c = 0
        t = (-2 * c) / (f0 + math.sqrt(f0 * f0 - 2 * a * c)) if a else -c / f0
        if t > t_end:
            break
        if t >= 0:
            out_t.append(t)
            out_r.append(m % 2)  # m even: φ ≡ π/2 (falling); odd: 3π/2 (rising)
        m += 1
    return np.array(out_t), np.array(out_r, dtype=np.uint8)


def _true_phase(t, f0, a, phi0):
    return 2 * math.pi * (f0 * t + 0.5 * a * t * t) + phi0


def test_phase_is_exact_at_the_crossings_and_follows_drift():
    f0, a, phi0 = 1570.0, 2000.0, 0.4  # 2 kHz/s drift: 1570 → 1572 Hz over 1 ms... and on
    zc, r = _chirp_crossings(f0, a, phi0, 0.05)
    ph = crossing_phases(zc, r)
    true = _true_phase(zc, f0, a, phi0)
    np.testing.assert_allclose(ph - ph[0], true - true[0], atol=1e-9)
    # between crossings the linear interpolation error is bounded by the chirp: 2π a (T/2)²/8
    t = np.linspace(zc[0], zc[-1], 5001)
    phase, valid = phase_from_zero_crossings(t, zc, r)
    assert valid.all()
    err = (phase - ph[0]) - (_true_phase(t, f0, a, phi0) - true[0])
    half = 0.5 / f0
    assert np.max(np.abs(err)) <= 2 * math.pi * a * half**2 / 8 * 1.01


@settings(max_examples=30, deadline=None)
@given(st.floats(1400, 1700), st.floats(0, 2 * math.pi),
       st.lists(st.floats(-0.02, 0.02), min_size=8, max_size=8))
def test_phase_recovery_exact_for_stepwise_frequency_drift(f0, phi0, steps):
    """Frequency drifting half-period by half-period: linear phase per segment, so exact."""
    # build crossing times whose half-periods drift; phase is linear in between by construction
    half = 0.5 / f0 * (1 + np.cumsum(np.array(steps)))
    first = ((math.pi / 2 - phi0) % (2 * math.pi)) / (2 * math.pi * f0)
    zc = first + np.concatenate([[0.0], np.cumsum(half)])
    rising = (np.arange(zc.size) + (0 if (phi0 + 2 * math.pi * f0 * first) % (2 * math.pi)
                                    < math.pi else 1)) % 2
    ph_c = crossing_phases(zc, rising)
    rng = np.random.default_rng(1)
    seg = rng.integers(0, zc.size - 1, 200)
    u = rng.random(200)
    t = zc[seg] + u * (zc[seg + 1] - zc[seg])
    phase, valid = phase_from_zero_crossings(t, zc, rising)
    expect = ph_c[seg] + u * math.pi
    np.testing.assert_allclose(phase, expect, atol=1e-9)
    assert valid.all()


def test_missed_crossing_steps_a_full_period():
    zc, r = _chirp_crossings(1570.0, 0.0, 0.1, 0.01)
    keep = np.ones(zc.size, bool)
    keep[5] = False
    ph_full = crossing_phases(zc, r)
    ph_missing = crossing_phases(zc[keep], r[keep])
    np.testing.assert_allclose(ph_missing, ph_full[keep], atol=1e-12)


def test_shots_outside_the_span_are_reported_not_guessed(system):
    zc, r = _chirp_crossings(1570.0, 0.0, 0.1, 0.01)
    t = np.array([zc[0] - 1e-6, zc[0], 0.5 * (zc[0] + zc[-1]), zc[-1], zc[-1] + 1e-6])
    theta, valid = scan_angles(t, zc, r, system.scanner)
    assert valid.tolist() == [False, True, True, True, False]
    assert np.isnan(theta[~valid]).all() and np.isfinite(theta[valid]).all()


def test_scan_angle_matches_the_true_trajectory(system):
    f0, phi0 = system.scanner.f_mech, 0.25
    zc, r = _chirp_crossings(f0, 0.0, phi0, 0.02)
    t = np.arange(zc[0], zc[-1], 1 / 20000.0)
    theta, valid = scan_angles(t, zc, r, system.scanner)
    expect = system.scanner.theta0 + theta_mech_trajectory(t, system.scanner.theta_mech_max, f0,
                                                            phi0)
    np.testing.assert_allclose(theta, expect, atol=1e-9)


@pytest.mark.parametrize("zc,rising,match", [
    ([0.1], [0], "at least 2"),
    ([], [], "at least 2"),
    ([0.1, 0.3, 0.2], [0, 1, 0], "strictly increasing"),
    ([0.1, 0.1], [0, 1], "strictly increasing"),
    ([0.1, np.nan], [0, 1], "finite"),
    ([0.1, 0.2], [0, 2], "0 \\(falling\\) or 1"),
    ([0.1, 0.2], [0], "shape"),
])
def test_bad_zero_crossings_are_rejected(zc, rising, match):
    with pytest.raises(FormatError, match=match):
        phase_from_zero_crossings([0.15], zc, rising)
