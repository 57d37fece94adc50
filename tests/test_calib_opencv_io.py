"""The calibrated system through cv2.FileStorage: YAML and XML, read by OpenCV and read back."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from mems_stereo.calib.opencv_io import (
    pose_from_scanner,
    read_opencv_covariance,
    read_opencv_system,
    write_opencv_system,
)

from mems_stereo.errors import FormatError
from mems_stereo.model.system import burkard2022, system_to_dict

NAMES = ["theta0", "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x", "baseline_z"]


@pytest.fixture
def calibrated():
    """A system as calibration leaves it: odd values, 8 distortion terms, σ and covariance."""
    rng = np.random.default_rng(5)
    s = burkard2022().with_params(theta0=0.7631234567890123, baseline_x=-0.12177777777777,
                                  baseline_z=0.00312345678901, tdc_offset=1.2345678901e-9,
                                  phase_offset=0.0123456789, fx=197.31415926535)
    rc = s.receiver
    ang = 0.0137
    e1 = np.array([np.cos(ang), 0.0, np.sin(ang)])
    e2 = np.array([-np.sin(ang) * 0.6, 0.8, np.cos(ang) * 0.6])
    e2 -= e1 * (e1 @ e2)
    e2 /= np.linalg.norm(e2)
    sc = s.scanner.__class__(**{**s.scanner.__dict__, "normal_basis": np.stack([e1, e2])})
    s = s.replace(scanner=sc, receiver=rc.__class__(**{**rc.__dict__,
                  "dist_coeffs": rng.normal(0, 1e-3, 8)}))
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-8
    std = np.sqrt(np.diag(cov))
    cal = {"parameters": {n: {"value": s.get_param(n), "std": float(std[i]), "initial": 0.0}
                          for i, n in enumerate(NAMES)},
           "rms_pixel": 0.29, "rms_time": 5.5e-9, "converged": True}
    s = s.replace(calibration=cal)
    res = SimpleNamespace(names=NAMES, covariance=cov, rms_pixel=0.29, rms_time=5.5e-9)
    return s, res


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".yaml.gz"])
def test_filestorage_reproduces_K_dist_R_T_exactly(calibrated, tmp_path, suffix):
    s, res = calibrated
    path = write_opencv_system(tmp_path / f"system{suffix}", s, res)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat()
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat()
    w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
    th0 = fs.getNode("theta0").real()
    fs.release()
    np.testing.assert_array_equal(K, s.receiver.camera_matrix)
    np.testing.assert_array_equal(dist.ravel(), s.receiver.dist_coeffs)
    R0, T0 = pose_from_scanner(s.scanner)
    np.testing.assert_array_equal(R, R0)
    np.testing.assert_array_equal(T.ravel(), s.scanner.position)
    assert (w, h) == tuple(s.receiver.image_size) and th0 == s.scanner.theta0
    # R is the projector's rotation: its first two columns are the mirror normal's basis
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(R[:, :2].T, s.scanner.normal_basis)


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_reading_back_gives_the_same_system(calibrated, tmp_path, suffix):
    s, res = calibrated
    path = write_opencv_system(tmp_path / f"system{suffix}", s, res)
    back = read_opencv_system(path)
    assert system_to_dict(back) == system_to_dict(s)
    names, cov = read_opencv_covariance(path)
    assert names == NAMES
    np.testing.assert_array_equal(cov, res.covariance)


def test_sigma_nodes_and_nan_for_unestimated(calibrated, tmp_path):
    s, res = calibrated
    path = write_opencv_system(tmp_path / "s.yml", s, res)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    t_std = fs.getNode("T_std").mat().ravel()
    th_std = fs.getNode("theta0_std").real()
    fs.release()
    cal = s.calibration["parameters"]
    assert th_std == cal["theta0"]["std"]
    assert t_std[0] == cal["baseline_x"]["std"] and np.isnan(t_std[1])
    # an uncalibrated system: every σ NaN, no covariance
    p2 = write_opencv_system(tmp_path / "nominal.xml", burkard2022())
    fs = cv2.FileStorage(str(p2), cv2.FILE_STORAGE_READ)
    assert np.isnan(fs.getNode("amplitude_std").real())
    assert fs.getNode("covariance").empty()
    fs.release()
    assert read_opencv_covariance(p2) == (None, None)


def test_bad_files_name_the_node(calibrated, tmp_path):
    s, _ = calibrated
    with pytest.raises(FormatError, match="json"):
        write_opencv_system(tmp_path / "s.json", s)
    fs = cv2.FileStorage(str(tmp_path / "other.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.eye(3))
    fs.release()
    with pytest.raises(FormatError, match="format"):
        read_opencv_system(tmp_path / "other.yml")
    path = write_opencv_system(tmp_path / "s.yml", s)
    text = path.read_text().replace("theta0:", "theta_zero:")
    path.write_text(text)
    with pytest.raises(FormatError, match="theta0"):
        read_opencv_system(path)
