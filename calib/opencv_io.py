"""The calibrated system through ``cv2.FileStorage`` (YAML or XML), for OpenCV users.

A C++ or Python program that already reads OpenCV calibration files opens
ours the same way: the receiver's intrinsics are under the names OpenCV's
calibration samples write (``camera_matrix``, ``distortion_coefficients``,
``image_width``, ``image_height``; ``dist_coeffs`` and ``image_size`` are
written too, as the C++ API names them), and the scanner is a *projector*
posed in the camera frame like the second camera of ``cv::stereoCalibrate``:

    X_cam = R · X_proj + T

with the projector frame's axes ``[e1, e2, e1 × e2]`` = the mirror normal's
basis (FORMAT v1 ``scanner.normal_basis``; the mirror normal at scan angle θ
is ``n(θ) = cos θ · e1 + sin θ · e2``) and origin at the mirror pivot, so
``R`` (3×3) has columns e1, e2, e1 × e2 and ``T`` (3×1, m) is the pivot
(``scanner.position``).  The scan model: ``theta0`` (rad), ``amplitude``
(θ_mech,max, rad), ``phase`` (phase offset, rad), ``tdc_offset`` (s), each
with ``<name>_std`` when the system was calibrated, ``T_std`` (3×1, m),
``camera_matrix_std`` (3×3, zeros where not estimated), and
``covariance`` (n×n, SI units) over ``covariance_parameters`` (a sequence
of names) with ``rms_pixel`` (px) and ``rms_time`` (s; a two-axis fit:
``rms_path``, m) when a calibration result is given (a
:class:`~mems_stereo.calib.result.CalibrationResult` or a two-axis
:class:`~mems_stereo.calib.twoaxis.TwoAxisCalibration`) or the system's
``calibration`` block holds them.  A σ that was not estimated is written as
NaN.  A two-axis system's second axis is written as ``scanner_axis2_json``
(its FORMAT v1 object) and read back.

Everything else the package needs to read the system back (laser
direction, f_mech, laser, TDC, pixel pitch, speed of light) is written too,
so :func:`read_opencv_system` returns the same :class:`System`.  The docs
show the C++ reader (``docs/interchange.md``).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.model.system import (
    TDC,
    Laser,
    Receiver,
    Scanner,
    System,
    system_from_dict,
    system_to_dict,
)
from mems_stereo.util.atomic import atomic_output

FORMAT_NAME = "mems-stereo/opencv-system"
#: FileStorage node ↔ system parameter (names of System.get_param / the calibration block)
SCALARS = {"theta0": "theta0", "amplitude": "theta_mech_max", "phase": "phase_offset",
           "tdc_offset": "tdc_offset"}


def pose_from_scanner(scanner: Scanner) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), T (3, 1))`` of the projector (mirror) frame in the camera frame, m."""
    e = np.asarray(scanner.normal_basis, dtype=np.float64)
    R = np.column_stack([e[0], e[1], np.cross(e[0], e[1])])
    T = np.asarray(scanner.position, dtype=np.float64).reshape(3, 1)
    return R, T


def _std(system: System, name: str) -> float:
    cal = system.calibration or {}
    p = cal.get("parameters", {}).get(name)
    if p and p.get("std") is not None:
        return float(p["std"])
    s = cal.get("std", {}).get(name)  # a two-axis calibration block
    return math.nan if s is None else float(s)


def _fit_summary(system: System, result) -> tuple[list, np.ndarray | None, dict]:
    """``(names, covariance, {node: RMS})`` of ``result`` (either calibration kind), else
    of the system's calibration block; ``([], None, {})`` when neither has them."""
    if result is not None:
        cov = getattr(result, "covariance", None)
        if cov is None:
            cov = getattr(result, "cov", None)
        if hasattr(result, "rms_time"):
            rms = {"rms_pixel": result.rms_pixel, "rms_time": result.rms_time}
        else:
            rms = {"rms_pixel": result.rms_px, "rms_path": result.rms_L}
        return list(result.names), cov, rms
    cal = system.calibration or {}
    c = cal.get("covariance") or {}
    rms = {k: cal[k] for k in ("rms_pixel", "rms_time") if cal.get(k) is not None}
    if cal.get("rms_px") is not None:
        rms = {"rms_pixel": cal["rms_px"], "rms_path": cal.get("rms_path_m", math.nan)}
    if c.get("names") and c.get("matrix") is not None:
        return list(c["names"]), np.asarray(c["matrix"], dtype=np.float64), rms
    return [], None, rms


def write_opencv_system(path: str | os.PathLike, system: System, result=None) -> Path:
    """Write ``system`` (and the covariance of ``result``, if given) as YAML or XML.

    The suffix picks the format (``.yml``/``.yaml`` or ``.xml``, optionally
    ``.gz``), as ``cv2.FileStorage`` does.  Written atomically.
    """
    import cv2

    p = Path(path)
    sfx = "".join(p.suffixes[-2:]) if p.suffix == ".gz" else p.suffix
    if sfx.removesuffix(".gz") not in (".yml", ".yaml", ".xml"):
        raise FormatError(f"expected a .yml, .yaml or .xml file name, found {p.name!r}", str(p))
    rc, sc = system.receiver, system.scanner
    R, T = pose_from_scanner(sc)
    with atomic_output(p, suffix=sfx) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("format", FORMAT_NAME)
            fs.write("version", 1)
            fs.write("image_width", int(rc.image_size[0]))
            fs.write("image_height", int(rc.image_size[1]))
            fs.write("image_size", np.array(rc.image_size, dtype=np.int32).reshape(1, 2))
            K = np.asarray(rc.camera_matrix, dtype=np.float64)
            dist = np.asarray(rc.dist_coeffs, dtype=np.float64).reshape(1, -1)
            fs.write("camera_matrix", K)
            fs.write("distortion_coefficients", dist)
            fs.write("dist_coeffs", dist)
            Kstd = np.zeros((3, 3))
            Kstd[0, 0], Kstd[0, 2] = _std(system, "fx"), _std(system, "cx")
            Kstd[1, 1], Kstd[1, 2] = _std(system, "fy"), _std(system, "cy")
            Kstd[np.isnan(Kstd)] = 0.0
            fs.write("camera_matrix_std", Kstd)
            fs.write("R", R)
            fs.write("T", T)
            fs.write("T_std", np.array([[_std(system, f"baseline_{a}")] for a in "xyz"]))
            for node, name in SCALARS.items():
                fs.write(node, float(system.get_param(name)))
                fs.write(f"{node}_std", _std(system, name))
            fs.write("laser_direction", np.asarray(sc.laser_direction, np.float64).reshape(3, 1))
            fs.write("f_mech", float(sc.f_mech))
            fs.write("f_rep", float(system.laser.f_rep))
            fs.write("pulse_fwhm", float(system.laser.pulse_fwhm))
            fs.write("wavelength", float(system.laser.wavelength))
            fs.write("tdc_bin_width", float(system.tdc.bin_width))
            fs.write("tdc_n_bins", int(system.tdc.n_bins))
            fs.write("pixel_pitch", np.asarray(rc.pixel_pitch, np.float64).reshape(1, 2))
            fs.write("spad_diameter", float(rc.spad_diameter))
            fs.write("speed_of_light", float(system.speed_of_light))
            if sc.axis2 is not None:
                fs.write("scanner_axis2_json", json.dumps(system_to_dict(system)["scanner"]
                                                          ["axis2"]))
            names, cov, rms = _fit_summary(system, result)
            if names and cov is not None:
                fs.write("covariance", np.asarray(cov, dtype=np.float64))
                fs.startWriteStruct("covariance_parameters", cv2.FileNode_SEQ)
                for n in names:
                    fs.write("", str(n))
                fs.endWriteStruct()
            for node, v in rms.items():
                fs.write(node, float(v))
            if system.calibration is not None:
                fs.write("calibration_json", json.dumps(system.calibration))
        finally:
            fs.release()
    return p


def _mat(fs, name: str, source: str, shape=None, required: bool = True):
    node = fs.getNode(name)
    if node.empty():
        if required:
            raise FormatError("required node is missing", source, name)
        return None
    m = node.mat()
    if m is None:
        raise FormatError("expected a matrix", source, name)
    m = np.asarray(m, dtype=np.float64)
    if shape is not None and m.shape != shape:
        raise FormatError(f"expected shape {shape}, found {m.shape}", source, name)
    return m


def _real(fs, name: str, source: str) -> float:
    node = fs.getNode(name)
    if node.empty() or not (node.isReal() or node.isInt()):
        raise FormatError("expected a number", source, name)
    return float(node.real())


def read_opencv_system(path: str | os.PathLike) -> System:
    """Read a file of :func:`write_opencv_system` back into the same :class:`System`.

    Raises :class:`FormatError` naming the node when one is missing or malformed.
    """
    import cv2

    source = str(path)
    if not Path(path).exists():
        raise FileNotFoundError(2, "file not found", source)
    fs = cv2.FileStorage(source, cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise FormatError("cv2.FileStorage cannot open it", source)
    try:
        fmt = fs.getNode("format").string()
        if fmt != FORMAT_NAME:
            raise FormatError(f"expected {FORMAT_NAME!r}, found {fmt!r}", source, "format")
        K = _mat(fs, "camera_matrix", source, (3, 3))
        dist = _mat(fs, "distortion_coefficients", source).ravel()
        size = (int(_real(fs, "image_width", source)), int(_real(fs, "image_height", source)))
        R = _mat(fs, "R", source, (3, 3))
        T = _mat(fs, "T", source, (3, 1)).ravel()
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise FormatError("expected a rotation matrix", source, "R")
        dl = _mat(fs, "laser_direction", source, (3, 1)).ravel()
        receiver = Receiver(K, dist, size, _mat(fs, "pixel_pitch", source, (1, 2)).ravel(),
                            _real(fs, "spad_diameter", source))
        scanner = Scanner(T, np.stack([R[:, 0], R[:, 1]]), dl, _real(fs, "theta0", source),
                          _real(fs, "f_mech", source), _real(fs, "amplitude", source),
                          _real(fs, "phase", source))
        laser = Laser(_real(fs, "f_rep", source), _real(fs, "pulse_fwhm", source),
                      _real(fs, "wavelength", source))
        tdc = TDC(_real(fs, "tdc_bin_width", source), int(_real(fs, "tdc_n_bins", source)),
                  _real(fs, "tdc_offset", source))
        cal_node = fs.getNode("calibration_json")
        cal = json.loads(cal_node.string()) if not cal_node.empty() else None
        system = System(receiver, scanner, laser, tdc, _real(fs, "speed_of_light", source), cal)
        axis2_node = fs.getNode("scanner_axis2_json")
        axis2 = None if axis2_node.empty() else axis2_node.string()
    finally:
        fs.release()
    d = system_to_dict(system)
    if axis2 is not None:
        try:
            d["scanner"]["axis2"] = json.loads(axis2)
        except ValueError as e:
            raise FormatError(f"expected a JSON object ({e})", source,
                              "scanner_axis2_json") from None
    # the system JSON's own validation (unit vectors, basis, coefficient counts)
    return system_from_dict(d, source)


def read_opencv_covariance(path: str | os.PathLike):
    """``(names, covariance (n, n))`` written with a CalibrationResult, or ``(None, None)``."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode("covariance_parameters")
        if node.empty():
            return None, None
        names = [node.at(i).string() for i in range(node.size())]
        return names, _mat(fs, "covariance", str(path), (len(names), len(names)))
    finally:
        fs.release()
