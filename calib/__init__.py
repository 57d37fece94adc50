"""Calibration of the scanner–receiver pair from flat-target recordings.

* :func:`calibrate_system` — classify → fit → reclassify → refit (the user's call);
* :func:`read_target_distances` — measured target distances from a JSON file;
* :func:`fit_detections` — the robust joint fit on signal detections;
* :class:`CalibrationResult` — estimates, σ, covariance, RMS, observability;
* :mod:`mems_stereo.calib.model` — forward model (beam → plane → pixel, path length);
* :mod:`mems_stereo.physics.first_photon_timing` — first-photon bias of a wide pulse
  behind a late TDC;
* :mod:`mems_stereo.calib.intrinsics` — receiver intrinsics from ChArUco images (2-D arrays);
* :mod:`mems_stereo.calib.synth` — synthetic detections for tests.

See ``docs/calibration.md``.
"""

from mems_stereo.calib.calibrate import calibrate_system, read_target_distances
from mems_stereo.calib.detections import TargetDetections, detections_from_labels
from mems_stereo.calib.fit import CalibrationResult, ObservabilityWarning, fit_detections

__all__ = ["CalibrationResult", "ObservabilityWarning", "TargetDetections",
           "calibrate_system", "detections_from_labels", "fit_detections",
           "read_target_distances"]
