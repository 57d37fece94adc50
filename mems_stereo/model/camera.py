"""The receiver as an OpenCV camera: pixel ↔ unit ray, through K and distortion.

Pixels are 0-based ``(column, row)`` with centres at integers (OpenCV).  Rays
are unit vectors in the receiver camera frame (x right, y down, z forward),
starting at the projection centre (the world origin).  A line sensor is a
camera of height 1 (row 0); everything here works for any ``image_size``.
"""

from __future__ import annotations

import cv2
import numpy as np

from mems_stereo.errors import ShapeError
from mems_stereo.model.hardware import ALLOWED_DIST_LENGTHS, Receiver, validate_camera_matrix


def check_intrinsics(camera_matrix, dist_coeffs=None) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert intrinsics: returns ((3, 3) float64, (D,) float64).

    Raises :class:`~mems_stereo.errors.FormatError` (a ``ValueError``) naming
    the expected and actual shape.
    """
    K = validate_camera_matrix(camera_matrix)
    if dist_coeffs is None:
        dist = np.zeros(5)
    else:
        dist = np.asarray(dist_coeffs, dtype=np.float64).ravel()
        if dist.size not in ALLOWED_DIST_LENGTHS:
            raise ShapeError(
                f"dist_coeffs: expected 4, 5, 8, 12 or 14 coefficients, found {dist.size}")
    return K, dist


def _as_points2(pixels) -> np.ndarray:
    p = np.asarray(pixels, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 2:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != 2:
        raise ShapeError(f"pixels: expected shape (N, 2), found {p.shape}")
    return p


def normalized_coordinates(pixels, camera_matrix, dist_coeffs=None) -> np.ndarray:
    """Undistorted normalised image coordinates (x/z, y/z) of pixels.

    ``pixels`` : (N, 2) float, (column, row).  Returns (N, 2) float64.
    Uses ``cv2.undistortPoints`` (iterative for non-zero distortion).
    """
    K, dist = check_intrinsics(camera_matrix, dist_coeffs)
    p = _as_points2(pixels)
    if p.shape[0] == 0:
        return np.zeros((0, 2))
    if not np.any(dist):
        x = (p[:, 0] - K[0, 2]) / K[0, 0]
        y = (p[:, 1] - K[1, 2]) / K[1, 1]
        return np.stack([x, y], axis=1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    out = cv2.undistortPoints(p.reshape(-1, 1, 2), K, dist, criteria=crit)
    return out.reshape(-1, 2).astype(np.float64)


def pixels_to_rays(pixels, camera_matrix, dist_coeffs=None) -> np.ndarray:
    """Unit viewing rays of pixels, (N, 3) float64, receiver camera frame (z > 0).

    Examples
    --------
    >>> K = ms.preset("burkard2022").receiver.camera_matrix
    >>> np.round(ms.pixels_to_rays(np.array([[95.5, 0.0], [0.0, 0.0]]), K), 4)
    array([[ 0.    ,  0.    ,  1.    ],
           [-0.4358,  0.    ,  0.9   ]])
    """
    xy = normalized_coordinates(pixels, camera_matrix, dist_coeffs)
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def project_points(points, camera_matrix, dist_coeffs=None) -> np.ndarray:
    """Pixels (column, row) of 3-D points, (N, 2) float64, via ``cv2.projectPoints``.

    ``points`` : (N, 3) metres, receiver camera frame.  Points with z <= 0
    (behind the camera) give NaN.

    Examples
    --------
    >>> K = ms.preset("burkard2022").receiver.camera_matrix
    >>> points = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.0, -1.0]])
    >>> np.round(ms.project_points(points, K), 2)
    array([[ 95.5 ,   0.  ],
           [144.81,   0.  ],
           [   nan,    nan]])
    """
    K, dist = check_intrinsics(camera_matrix, dist_coeffs)
    P = np.asarray(points, dtype=np.float64)
    if P.ndim == 1 and P.shape[0] == 3:
        P = P[None]
    if P.ndim != 2 or P.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), found {P.shape}")
    out = np.full((P.shape[0], 2), np.nan)
    front = P[:, 2] > 0
    if not np.any(dist):  # the pinhole: OpenCV's operations, in its order
        return _pinhole(P, K, front, out)
    if np.any(front):
        img, _ = cv2.projectPoints(P[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
        out[front] = img.reshape(-1, 2)
    return out


def _pinhole(P, K, front, out) -> np.ndarray:
    """:func:`project_points` without distortion: ``cv2.projectPoints``'s arithmetic
    with zero coefficients, the same bits (tested): x = X·(1/Z), y = Y·(1/Z) (the
    distortion factors are exactly 1 and the added terms 0 for finite x, y; NaN for
    both where either is not finite), column = x·fx + cx, row = y·fy + cy.  ``out``
    (N, 2) NaN, written at the rows ``front`` (Z > 0)."""
    with np.errstate(invalid="ignore", over="ignore"):
        z = 1.0 / P[front, 2]
        x = P[front, 0] * z
        y = P[front, 1] * z
        ok = np.isfinite(x) & np.isfinite(y)
        out[front, 0] = np.where(ok, x * K[0, 0] + K[0, 2], np.nan)
        out[front, 1] = np.where(ok, y * K[1, 1] + K[1, 2], np.nan)
    return out


def pixel_grid(image_size) -> np.ndarray:
    """All pixel centres, (H*W, 2) float64 (column, row), row-major like ``bins[k]``."""
    w, h = int(image_size[0]), int(image_size[1])
    rows, cols = np.mgrid[0:h, 0:w]
    return np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)


def receiver_rays(receiver: Receiver) -> np.ndarray:
    """Unit rays of every pixel of a receiver, (H, W, 3) float64, camera frame.

    Examples
    --------
    >>> rays = ms.receiver_rays(ms.preset("burkard2022").receiver)
    >>> rays.shape, np.round(rays[0, 0], 4)
    ((1, 192, 3), array([-0.4358,  0.    ,  0.9   ]))
    """
    rays = pixels_to_rays(pixel_grid(receiver.image_size), receiver.camera_matrix,
                          receiver.dist_coeffs)
    return rays.reshape(receiver.height, receiver.width, 3)


def receiver_ray_derivatives(receiver: Receiver, step: float = 1e-3):
    """∂ray/∂column and ∂ray/∂row of every pixel, each (H, W, 3), per pixel.

    Central differences of :func:`pixels_to_rays` (exact for no distortion up
    to rounding), used to propagate the pixel's extent into angles.
    """
    g = pixel_grid(receiver.image_size)
    K, d = receiver.camera_matrix, receiver.dist_coeffs
    shape = (receiver.height, receiver.width, 3)
    du = (pixels_to_rays(g + [step, 0], K, d) - pixels_to_rays(g - [step, 0], K, d)) / (2 * step)
    dv = (pixels_to_rays(g + [0, step], K, d) - pixels_to_rays(g - [0, step], K, d)) / (2 * step)
    return du.reshape(shape), dv.reshape(shape)
