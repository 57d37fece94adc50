"""Epipolar constraint of the scanner–receiver pair and midpoint triangulation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mems_stereo.geometry.epipolar import (
    epipolar_pixels,
    epipolar_residual,
    epipolar_segment,
    path_for_range,
    triangulate_midpoint,
)
from mems_stereo.model.camera import pixels_to_rays, project_points
from mems_stereo.model.scanner import scan_direction
from mems_stereo.model.system import Receiver, burkard2022

vec = st.lists(st.floats(-2, 2, allow_nan=False), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(vec, vec.filter(lambda v: np.linalg.norm(v) > 0.05), st.floats(0.5, 20))
def test_residual_vanishes_for_a_consistent_pair_and_grows_with_offset(b, x_dir, dist):
    """A point seen from the scanner at b and from the origin satisfies d·(b × l) = 0."""
    x = x_dir / np.linalg.norm(x_dir) * dist
    if np.linalg.norm(x - b) < 1e-3 or np.linalg.norm(np.cross(b, x)) < 1e-3:
        return
    d = (x - b) / np.linalg.norm(x - b)
    l = x / np.linalg.norm(x)
    assert abs(epipolar_residual(d, b, l)) < 1e-12 * max(1, np.linalg.norm(b))
    # move the point off the epipolar plane by e along its normal: |residual| grows with e
    n = np.cross(b, d)
    n /= np.linalg.norm(n)
    res = []
    for e in (1e-3, 1e-2, 1e-1):
        l2 = (x + e * n) / np.linalg.norm(x + e * n)
        res.append(abs(epipolar_residual(d, b, l2)))
    assert res[0] < res[1] < res[2]


def test_line_sensor_pair_is_always_epipolar(system):
    """Paper geometry: scanner ray and every pixel ray lie in the x–z plane (y = 0)."""
    rays = pixels_to_rays(np.stack([np.arange(192.0), np.zeros(192)], 1),
                          system.receiver.camera_matrix)
    d = scan_direction(np.linspace(0.55, 0.97, 7), system.scanner)
    r = epipolar_residual(d[:, None], system.baseline, rays[None])
    assert np.abs(r).max() < 1e-15


@settings(max_examples=40, deadline=None)
@given(vec, vec, vec, vec)
def test_midpoint_matches_cv_triangulate_on_consistent_pairs(x, c2, rv1, rv2):
    """Two ordinary cameras see a point: midpoint = cv2.triangulatePoints = the point."""
    x = x + np.array([0, 0, 6.0])
    c1 = np.zeros(3)
    c2 = c2 * 0.5 + np.array([0.3, 0, 0])
    if np.linalg.norm(np.cross(x - c1, x - c2)) < 1e-2 * np.linalg.norm(x - c1) * np.linalg.norm(
            x - c2):
        return
    R2, _ = cv2.Rodrigues(rv2 * 0.1)
    t2 = -R2 @ c2
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K @ np.hstack([R2, t2[:, None]])
    x2c = R2 @ x + t2
    if x2c[2] <= 0.1:
        return
    u1 = project_points(x[None], K)
    u2 = project_points(x2c[None], K)
    X = cv2.triangulatePoints(P1, P2, u1.T, u2.T)
    X = (X[:3] / X[3]).ravel()
    d1 = pixels_to_rays(u1, K)[0]
    d2 = R2.T @ pixels_to_rays(u2, K)[0]
    res = triangulate_midpoint(c1, d1, c2, d2)
    assert res.ok[0] and res.gap[0] < 1e-6
    np.testing.assert_allclose(res.points[0], x, atol=1e-6 * np.linalg.norm(x))
    np.testing.assert_allclose(res.points[0], X, atol=1e-5 * np.linalg.norm(x))


def test_midpoint_of_skew_rays_is_the_middle_of_the_common_perpendicular():
    o1, d1 = np.array([0.0, 0, 0]), np.array([1.0, 0, 0])
    o2, d2 = np.array([0.0, 1, 1]), np.array([0.0, 1, 0])
    res = triangulate_midpoint(o1, d1, o2, d2)
    np.testing.assert_allclose(res.points[0], [0, 0, 0.5])
    np.testing.assert_allclose(res.k[0], [0.0, -1.0])
    assert res.gap[0] == pytest.approx(1.0)
    # parallel rays: no unique solution -> NaN and flag
    res = triangulate_midpoint(o1, d1, o2, d1)
    assert not res.ok[0] and np.isnan(res.points).all()


def test_path_for_range_gives_points_at_that_range(system):
    d = scan_direction(system.scanner.theta0, system.scanner)
    r = np.array([0.5, 1.0, 5.0, 50.0])
    s = path_for_range(system.scanner.position, d, r)
    pts = system.scanner.position + s[:, None] * d
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), r, rtol=1e-12)


def test_epipolar_segment_of_the_line_sensor(system):
    d = scan_direction(system.scanner.theta0, system.scanner)
    seg = epipolar_segment(system, d, 1.0, 20.0, n_samples=5)
    assert np.allclose(seg[:, 1], 0.0)
    assert np.all(np.diff(seg[:, 0]) > 0)  # farther -> towards the vanishing point
    # at the working distance the beam is on the optical axis: column cx
    mid = epipolar_segment(system, d, 2.5, 2.5 + 1e-9, n_samples=2)
    assert mid[0, 0] == pytest.approx(system.receiver.camera_matrix[0, 2], abs=0.05)
    px = epipolar_pixels(system, d, 1.0, 20.0)
    assert px[0, 0] == np.floor(seg[0, 0] + 0.5) and px[-1, 0] == np.floor(seg[-1, 0] + 0.5)
    assert np.all(np.diff(px[:, 0]) == 1)


def test_epipolar_band_of_a_2d_array_is_narrow():
    """A 2-axis geometry: only pixels near the projected beam are read out."""
    s = burkard2022()
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    rec = Receiver(K, np.zeros(5), (320, 240), np.array([1e-5, 1e-5]), 5e-6)
    s2 = s.replace(receiver=rec)
    d = np.array([0.1, 0.05, 1.0])
    d /= np.linalg.norm(d)
    px = epipolar_pixels(s2, d, 0.5, 30.0)
    assert 0 < len(px) < 3 * 320
    seg = epipolar_segment(s2, d, 0.5, 30.0, n_samples=200)
    # every selected pixel is within 0.5 px (each axis) of the projected ray
    dist = np.min(np.abs(px[:, None, :] - seg[None]).max(axis=2), axis=1)
    assert dist.max() <= 0.5 + 0.2
