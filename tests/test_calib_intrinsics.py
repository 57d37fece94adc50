"""ChArUco intrinsics (OpenCV 5 CharucoDetector API) on rendered views with a known K."""

from __future__ import annotations

import cv2
import numpy as np
from mems_stereo.calib.intrinsics import (
    calibrate_charuco,
    default_poses,
    make_board,
    synthetic_charuco_views,
)

K_TRUE = np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]])


def test_rendered_corners_match_projectpoints():
    """The renderer is right: detected corners sit where cv2.projectPoints puts them."""
    board = make_board()
    rvec, tvec = default_poses()[1]
    img = synthetic_charuco_views(board, K_TRUE, (640, 480), [(rvec, tvec)])[0]
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(img)
    assert ids is not None and len(ids) >= 12
    obj = board.getChessboardCorners()[np.asarray(ids).ravel()]
    proj, _ = cv2.projectPoints(obj, np.array(rvec, float), np.array(tvec, float), K_TRUE,
                                np.zeros(5))
    err = np.linalg.norm(proj.reshape(-1, 2) - np.asarray(corners).reshape(-1, 2), axis=1)
    assert np.median(err) < 0.5


def test_calibrate_recovers_camera_matrix():
    board = make_board()
    views = synthetic_charuco_views(board, K_TRUE, (640, 480), default_poses(), px_per_m=2500)
    res = calibrate_charuco(views, board, flags=cv2.CALIB_FIX_K3)
    assert res.n_views == 6 and res.rms < 1.0
    got = res.camera_matrix[[0, 1, 0, 1], [0, 1, 2, 2]]
    want = K_TRUE[[0, 1, 0, 1], [0, 1, 2, 2]]
    assert np.all(np.abs(got - want) < 3 * res.std[:4] + 1e-9)
    assert abs(got[0] / 600.0 - 1) < 0.03
