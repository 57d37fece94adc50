"""dtof triangulation: closed forms against root finding, the paper's 2-D form, degenerate cases."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from mems_stereo.geometry.triangulation import (
    FLAG_BEHIND,
    FLAG_GRAZING,
    FLAG_NO_SOLUTION,
    beam_angle,
    coplanar_ray_intersection,
    epipolar_stereo_point,
    paper_eq8_z,
    paper_eq9_x,
    paper_mu_pix,
    path_length_of_point,
    pixel_ray_point,
    scanner_ray_point,
    stereo_point,
)
from mems_stereo.model.camera import pixels_to_rays
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.tdc import codes_from_path_length, path_length_from_codes

unit = st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1).map(lambda v: v / np.linalg.norm(v))
pos = st.lists(st.floats(-0.5, 0.5, allow_nan=False), min_size=3, max_size=3).map(np.array)


@settings(max_examples=80, deadline=None)
@given(pos, unit, st.floats(0.01, 50.0))
def test_scanner_ray_root_matches_brentq(p, d, extra):
    """s solves |x − p| + |x| = L on the ray; scipy finds the same root."""
    L = np.linalg.norm(p) + extra
    x, s, flags = scanner_ray_point(p, d[None], np.array([L]))
    f = lambda t: t + np.linalg.norm(p + t * d) - L  # noqa: E731
    ref = brentq(f, 0.0, L, xtol=1e-13)
    if flags[0] == 0:
        assert abs(s[0] - ref) <= 1e-9 * max(1.0, L)
        assert abs(path_length_of_point(x, p)[0] - L) <= 1e-9 * max(1.0, L)
        # on the ray
        assert np.linalg.norm(np.cross(x[0] - p, d)) <= 1e-9 * max(1.0, L)
    else:  # only "behind the receiver" may be flagged for a valid L
        assert flags[0] == FLAG_BEHIND and (p + ref * d)[2] <= 1e-9 * L


@settings(max_examples=80, deadline=None)
@given(pos, unit.filter(lambda v: v[2] > 0.05), st.floats(0.01, 50.0))
def test_pixel_ray_root_matches_brentq(p, l, extra):
    L = np.linalg.norm(p) + extra
    x, rho, flags = pixel_ray_point(p, l[None], np.array([L]))
    f = lambda r: r + np.linalg.norm(r * l - p) - L  # noqa: E731
    ref = brentq(f, 0.0, L, xtol=1e-13)
    assert flags[0] == 0
    assert abs(rho[0] - ref) <= 1e-9 * max(1.0, L)
    assert abs(path_length_of_point(x, p)[0] - L) <= 1e-9 * max(1.0, L)


def test_no_solution_and_grazing_give_nan_and_flags():
    p = np.array([-0.125, 0.0, 0.0])
    d = np.array([[0.0, 0.0, 1.0]] * 3)
    x, s, fl = scanner_ray_point(p, d, np.array([0.1, 0.125, np.nan]))
    assert np.all(np.isnan(x)) and np.all(np.isnan(s))
    assert np.all(fl & FLAG_NO_SOLUTION)
    # parallel stereo rays
    sp = stereo_point(p, np.array([[0, 0, 1.0]]), np.array([[0, 0, 1.0]]))
    assert np.all(np.isnan(sp.points)) and sp.flags[0] & FLAG_GRAZING
    # rays that meet behind the receiver
    sp = stereo_point(p, np.array([[-0.3, 0, 1.0]]) / np.hypot(0.3, 1), np.array([[0, 0, 1.0]]))
    assert np.all(np.isnan(sp.points)) and sp.flags[0] & FLAG_BEHIND


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.2, 0.2), st.floats(0.3, 40.0))
def test_stereo_and_tof_agree_on_a_noise_free_detection(dtheta, dist):
    """Pixel ray through the beam's point: stereo, both ToF forms and coplanar closed form agree."""
    from mems_stereo.model.system import burkard2022

    sys_ = burkard2022()
    p = sys_.scanner.position
    d = scan_direction(np.array([sys_.scanner.theta0 + dtheta]), sys_.scanner)
    x = p + dist * d
    if x[0, 2] <= 0.05:
        return
    l = x / np.linalg.norm(x)
    L = path_length_of_point(x, p)
    sp = stereo_point(p, d, l)
    assert sp.flags[0] == 0 and np.allclose(sp.points, x, atol=1e-7 * dist) and sp.gap[0] < 1e-7
    assert np.allclose([sp.s[0], sp.rho[0]], [dist, np.linalg.norm(x)], rtol=1e-6)
    assert np.allclose(scanner_ray_point(p, d, L)[0], x, atol=1e-9 * dist)
    assert np.allclose(pixel_ray_point(p, l, L)[0], x, atol=1e-9 * dist)
    ep = epipolar_stereo_point(p, d, l)
    assert ep.flags[0] == 0 and np.allclose(ep.points, x, atol=1e-7 * dist)
    # a pixel ray tilted out of the epipolar plane projects back onto the same point
    tilt = l + np.array([[0.0, 0.01, 0.0]])
    ep = epipolar_stereo_point(p, d, tilt / np.linalg.norm(tilt))
    assert np.allclose(ep.points, x, atol=1e-6 * dist) and abs(ep.out_of_plane[0]) > 1e-3
    s2, rho2 = coplanar_ray_intersection(p, d, l)
    assert np.allclose([s2[0], rho2[0]], [dist, np.linalg.norm(x)], rtol=1e-7)


def test_paper_eq8_eq9_reproduce_the_3d_point(system):
    """The restored 2-D Eq. 8 (Z) and Eq. 9 (X) give the 3-D closed form's point."""
    th = system.scanner.theta0 + np.linspace(-0.2, 0.2, 9)
    d = scan_direction(th, system.scanner)
    p = system.scanner.position
    x = p + np.linspace(0.5, 30, 9)[:, None] * d
    L = path_length_of_point(x, p)
    Z = paper_eq8_z(L, beam_angle(d), p[0])
    assert np.allclose(Z, x[:, 2], rtol=1e-10)
    # Eq. 9 with the pixel where the point images (continuous column)
    K = system.receiver.camera_matrix
    col = K[0, 2] + K[0, 0] * x[:, 0] / x[:, 2]
    f = K[0, 0] * system.receiver.pixel_pitch[0]
    X = paper_eq9_x(paper_mu_pix(col, system), Z, f)
    assert np.allclose(X, x[:, 0], rtol=1e-10, atol=1e-12)
    # Eq. 10: u = 1 is column 0, μ = (96.5 − u)·w
    assert np.isclose(paper_mu_pix(0, system), 95.5 * system.receiver.pixel_pitch[0])
    ray = pixels_to_rays(np.array([[col[0], 0.0]]), K)
    assert np.allclose(ray[0], x[0] / np.linalg.norm(x[0]))


def test_codes_round_trip(system):
    codes = np.array([0, 1, 17, 4096])
    L = path_length_from_codes(codes, system.tdc, system.speed_of_light)
    assert np.isnan(L[0])
    assert np.allclose(codes_from_path_length(L[1:], system.tdc, system.speed_of_light), codes[1:])
    assert np.isclose(L[2], system.speed_of_light * 16.5 * 312.5e-12)
