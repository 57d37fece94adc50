"""Receiver camera: our pixel ↔ ray against OpenCV, line sensor and 2-D array."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mems_stereo.errors import FormatError, GeometryError
from mems_stereo.model.camera import (
    check_intrinsics,
    pixel_grid,
    pixels_to_rays,
    project_points,
    receiver_ray_derivatives,
    receiver_rays,
)

K2D = np.array([[600.0, 0.0, 319.5], [0.0, 610.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])


def test_line_sensor_rays_match_pinhole_closed_form(system):
    rays = receiver_rays(system.receiver)
    assert rays.shape == (1, 192, 3)
    K = system.receiver.camera_matrix
    cols = np.arange(192)
    x = (cols - K[0, 2]) / K[0, 0]
    expect = np.stack([x, np.zeros_like(x), np.ones_like(x)], 1)
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    np.testing.assert_allclose(rays[0], expect, atol=1e-12)
    # the paper's sensor frame: x = (96.5 − u)·w with u = c + 1 (1-based), image inverted
    w = system.receiver.pixel_pitch[0]
    f = K[0, 0] * w
    np.testing.assert_allclose(-x * f, (96.5 - (cols + 1)) * w, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.floats(-0.3, 0.3), st.floats(-0.2, 0.2), st.floats(0.5, 20.0))
def test_projection_matches_opencv_and_round_trips(x, y, z):
    P = np.array([[x * z, y * z, z]])
    ours = project_points(P, K2D, DIST)
    cv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K2D, DIST)
    np.testing.assert_allclose(ours, cv.reshape(-1, 2), atol=1e-9)
    ray = pixels_to_rays(ours, K2D, DIST)[0]
    np.testing.assert_allclose(ray, P[0] / np.linalg.norm(P[0]), atol=2e-7)


def test_distortion_free_fast_path_equals_opencv(rng):
    px = rng.uniform([0, 0], [640, 480], size=(200, 2))
    cv = cv2.undistortPoints(px.reshape(-1, 1, 2), K2D, np.zeros(5)).reshape(-1, 2)
    ours = pixels_to_rays(px, K2D)
    np.testing.assert_allclose(ours[:, :2] / ours[:, 2:], cv, atol=1e-9)


def test_points_behind_the_camera_give_nan():
    out = project_points([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]], K2D)
    assert np.isnan(out[0]).all() and np.allclose(out[1], [319.5, 239.5])


def test_pixel_grid_is_row_major():
    g = pixel_grid((3, 2))
    assert g.tolist() == [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]]


def test_ray_derivatives_match_finite_differences(system):
    du, dv = receiver_ray_derivatives(system.receiver)
    K = system.receiver.camera_matrix
    c = 40.0
    h = 1e-4
    num = (pixels_to_rays([[c + h, 0]], K) - pixels_to_rays([[c - h, 0]], K)) / (2 * h)
    np.testing.assert_allclose(du[0, 40], num[0], atol=1e-9)
    assert du.shape == dv.shape == (1, 192, 3)


@pytest.mark.parametrize("K,match", [
    (np.eye(2), r"expected shape \(3, 3\), found \(2, 2\)"),
    (np.zeros((3, 3)), "positive focal"),
    ([[1, 0, 0], [0, 1, 0], [0, 1, 1]], r"\[0, 0, 1\]"),
    ([[1, 0.5, 0], [0, 1, 0], [0, 0, 1]], "zero skew"),
])
def test_bad_camera_matrix_is_rejected(K, match):
    with pytest.raises(FormatError, match=match):
        check_intrinsics(K)


def test_bad_shapes_are_rejected():
    with pytest.raises(GeometryError, match="dist_coeffs"):
        check_intrinsics(K2D, [0.0, 0.1, 0.2])
    with pytest.raises(GeometryError, match=r"\(N, 2\)"):
        pixels_to_rays(np.zeros((4, 3)), K2D)
    with pytest.raises(GeometryError, match=r"\(N, 3\)"):
        project_points(np.zeros((4, 2)), K2D)


def test_distortion_free_projection_has_opencvs_bits(rng):
    # without distortion project_points does OpenCV's arithmetic in NumPy: the same bits
    # (a divide X/Z in place of X·(1/Z) would differ in a tenth of the points)
    n = 20000
    P = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-1, 1, n) * rng.integers(0, 2, n),
                         rng.uniform(0.05, 10, n)])
    P[:5] = [[0.0, -0.0, 1.0], [-0.0, 0.0, 2.0], [1e300, 0.0, 1e-300], [np.nan, 0.0, 1.0],
             [0.0, np.inf, 1.0]]
    for K in (K2D, np.array([[197.2, 0.0, 95.5], [0.0, 38.2, 0.0], [0.0, 0.0, 1.0]])):
        ours = project_points(P, K, np.zeros(5))
        cv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.zeros(5))
        cv = cv.reshape(-1, 2)
        assert np.array_equal(ours.view(np.int64)[~np.isnan(cv)],
                              cv.view(np.int64)[~np.isnan(cv)])
        assert np.array_equal(np.isnan(ours), np.isnan(cv))
