"""Calibration of the scanner–receiver pair from flat-wall recordings.

* :func:`calibrate_system` — recordings → :class:`CalibrationResult`, or a
  :class:`CalibrationFailure` (falsy, no system) saying why;
* :func:`calibrate_scanner_camera` — the same in calib3d's terms (RMS, system,
  σ, per target);
* :func:`read_target_distances` — measured wall distances from a JSON file;
* modules in data-flow order: :mod:`.association` (recordings → cells, background),
  :mod:`.track` (the beam's track on the sensor), :mod:`.initialisation` (global
  start values), :mod:`.problem` (parameters and the first-photon likelihood),
  :mod:`.solver` (the likelihood fit), :mod:`.missed` (walls the start missed),
  :mod:`.checks` (plausibility), :mod:`.fit` (the calibration's steps in order),
  :mod:`.observability` (covariance, verdict, consistency), :mod:`.result`;
  :mod:`.model` (beam → plane → pixel), :mod:`.family` (the family of
  recordings the calibration is proven on), :mod:`.intrinsics` (ChArUco).

See ``docs/calibration.md``.
"""

from mems_stereo.calib.calibrate import (
    ScannerCameraCalibration,
    calibrate_scanner_camera,
    calibrate_system,
    read_target_distances,
)
from mems_stereo.calib.fit import fit_walls
from mems_stereo.calib.result import CalibrationFailure, CalibrationResult

__all__ = ["CalibrationFailure", "CalibrationResult", "ScannerCameraCalibration",
           "calibrate_scanner_camera",
           "calibrate_system", "fit_walls", "read_target_distances"]
