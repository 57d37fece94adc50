"""Receiver intrinsics of a 2-D SPAD array from ChArUco board images (OpenCV 5).

A 2-D array is an ordinary camera: image a ChArUco board in several poses,
detect its corners with ``cv2.aruco.CharucoDetector(board).detectBoard``,
match them to board coordinates with ``board.matchImagePoints`` and run
``cv2.calibrateCamera``.  (OpenCV 5 removed ``interpolateCornersCharuco`` and
``calibrateCameraCharuco``.)  :func:`synthetic_charuco_views` renders a small
set of views with a known camera matrix (``board.generateImage`` and a
homography warp) for tests and as a sample:

    python -m mems_stereo.calib.intrinsics OUT_DIR      # writes view_*.png and K_true.txt

A line sensor (one row) cannot image a board: see ``docs/calibration.md``
for how its focal length and principal point are found, and the joint fit
(``free=("fx", "cx")``) for refining them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mems_stereo.errors import GeometryError


def make_board(squares=(7, 5), square_length: float = 0.04, marker_length: float = 0.03,
               dictionary: int = cv2.aruco.DICT_4X4_50):
    """A ChArUco board (squares x, y; lengths in metres)."""
    d = cv2.aruco.getPredefinedDictionary(dictionary)
    return cv2.aruco.CharucoBoard(tuple(squares), square_length, marker_length, d)


def synthetic_charuco_views(board, camera_matrix, image_size, poses, px_per_m: float = 5000.0):
    """Render the board seen by a pinhole camera (no distortion) in each pose.

    Parameters
    ----------
    board : cv2.aruco.CharucoBoard.
    camera_matrix : (3, 3) float64.
    image_size : (width, height) pixels.
    poses : list of (rvec (3,), tvec (3,)), board → camera, metres.
    px_per_m : resolution of the flat board image.

    Returns a list of (height, width) uint8 images.
    """
    K = np.asarray(camera_matrix, dtype=np.float64)
    sx, sy = board.getChessboardSize()
    L = board.getSquareLength()
    size_px = (int(sx * L * px_per_m), int(sy * L * px_per_m))
    flat = board.generateImage(size_px, marginSize=0, borderBits=1)
    # flat-image pixel (u, v) ↔ board point ((u, v) + ½) / px_per_m, z = 0 (board frame)
    # (pixel centres at integers: flat pixel u covers board x in [u, u+1) / px_per_m)
    S = np.array([[1.0 / px_per_m, 0.0, 0.5 / px_per_m], [0.0, 1.0 / px_per_m, 0.5 / px_per_m],
                  [0.0, 0.0, 1.0]])
    views = []
    for rvec, tvec in poses:
        R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
        Hm = K @ np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, dtype=np.float64)]) @ S
        img = cv2.warpPerspective(flat, Hm, tuple(int(v) for v in image_size),
                                  flags=cv2.INTER_AREA, borderValue=255)
        views.append(img)
    return views


@dataclass
class IntrinsicsResult:
    """cv2.calibrateCamera outcome: rms (px), camera_matrix (3, 3), dist_coeffs (D,),
    std (intrinsics σ as returned by calibrateCameraExtended), n_views used."""

    rms: float
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    std: np.ndarray
    n_views: int


def calibrate_charuco(images, board, flags: int = 0, min_corners: int = 6) -> IntrinsicsResult:
    """Camera matrix and distortion from ChArUco views (OpenCV 5 API).

    ``images`` : list of (H, W) uint8.  Views with fewer than ``min_corners``
    corners are skipped; fewer than 3 usable views raise GeometryError.
    """
    det = cv2.aruco.CharucoDetector(board)
    obj_pts, img_pts = [], []
    size = None
    for img in images:
        size = (img.shape[1], img.shape[0])
        corners, ids, _, _ = det.detectBoard(img)
        if ids is None or len(ids) < min_corners:
            continue
        op, ip = board.matchImagePoints(corners, ids)
        obj_pts.append(op.reshape(-1, 3).astype(np.float32))
        img_pts.append(ip.reshape(-1, 2).astype(np.float32))
    if len(obj_pts) < 3:
        raise GeometryError(f"ChArUco calibration: expected at least 3 views with "
                            f">= {min_corners} corners, found {len(obj_pts)}")
    rms, K, dist, _, _, std_i, _, _ = cv2.calibrateCameraExtended(
        obj_pts, img_pts, size, None, None, flags=flags)
    return IntrinsicsResult(float(rms), K, dist.ravel(), std_i.ravel(), len(obj_pts))


def default_poses():
    """Six board poses (rvec, tvec) around 0.5 m, tilted up to ~0.35 rad."""
    return [((0.0, 0.0, 0.0), (-0.14, -0.10, 0.55)), ((0.3, 0.0, 0.0), (-0.14, -0.10, 0.6)),
            ((0.0, 0.35, 0.0), (-0.16, -0.10, 0.6)), ((-0.25, 0.2, 0.1), (-0.12, -0.09, 0.5)),
            ((0.2, -0.3, -0.1), (-0.12, -0.11, 0.65)), ((-0.1, -0.2, 0.2), (-0.13, -0.12, 0.58))]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0] if argv else "charuco_sample")
    out.mkdir(parents=True, exist_ok=True)
    K = np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]])
    views = synthetic_charuco_views(make_board(), K, (640, 480), default_poses())
    for i, v in enumerate(views):
        cv2.imwrite(str(out / f"view_{i}.png"), v)
    np.savetxt(out / "K_true.txt", K)
    print(f"wrote {len(views)} views to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
