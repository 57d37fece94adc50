"""mems-stereo: calibration, dtof triangulation and point clouds for MEMS-scanning SPAD lidar.

The scanner and the SPAD receiver form a projector–camera stereo pair
(Burkard et al., J. Optical Microsystems 2(1), 011005, 2022).  Free functions
on NumPy arrays, in layers that follow the data (docs/architecture.md); a
layer imports only the layers above it in this list:

* :mod:`mems_stereo.errors`    the exception hierarchy
* :mod:`mems_stereo.util`      atomic writes, JSON reading with line/column errors
* :mod:`mems_stereo.model`     system (FORMAT v1, presets), scanner, camera, TDC convention,
  acquisition statistics
* :mod:`mems_stereo.physics`   pulse, first photon, spot, background, link budget
* :mod:`mems_stereo.geometry`  epipolar constraint, triangulation, uncertainty
* :mod:`mems_stereo.io`        recordings, labels, histograms, real data
* :mod:`mems_stereo.pipeline`  settings → angles → consistency/intervals → pass1 → peaks →
  pass2 → fusion → cloud; run (process_recording), distributed (Dask), timetags
* :mod:`mems_stereo.sim`       the simulator;  :mod:`mems_stereo.calib`  calibration
* :mod:`mems_stereo.viz`       export, render, plots (Open3D, matplotlib);  ``cli``  the commands

Frames, units and angles: ``docs/conventions.md``.  The core never imports
:mod:`mems_stereo.viz`, Open3D or matplotlib; those load in the viz layer only
(``mems_stereo.viz.cloud_to_open3d(cloud)`` gives an Open3D point cloud).
"""

import importlib

from mems_stereo import data
from mems_stereo.errors import FormatError, GeometryError, MemsStereoError, NotObservableError
from mems_stereo.geometry.epipolar import (
    epipolar_pixels,
    epipolar_residual,
    epipolar_segment,
    triangulate_midpoint,
)
from mems_stereo.io.recording import Recording, iter_shot_chunks, read_recording, write_recording
from mems_stereo.model.acquisition import acquisition_statistics, shot_pixels
from mems_stereo.model.camera import pixels_to_rays, project_points, receiver_rays
from mems_stereo.model.scanner import (
    mirror_normal,
    phase_from_zero_crossings,
    reflect,
    scan_angles,
    scan_direction,
    theta0_exact,
    theta0_small_angle,
)
from mems_stereo.model.system import (
    PRESETS,
    System,
    load_system,
    preset,
    save_system,
    system_from_dict,
    system_to_dict,
)
from mems_stereo.physics.background import background_rate_mle
from mems_stereo.pipeline.histograms import accumulate_histograms, moving_average

#: loaded on first use (the pipeline loads numba): ``ms.process_recording``, ...
_LAZY = {"process_recording": "mems_stereo.pipeline.run",
         "classify_recording": "mems_stereo.pipeline.pass1",
         "Settings": "mems_stereo.pipeline.settings",
         "PointCloud": "mems_stereo.pipeline.cloud",
         "iter_frames": "mems_stereo.pipeline.frames"}


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mems_stereo' has no attribute {name!r}")

__version__ = "0.1.0"

__all__ = [
    "accumulate_histograms", "background_rate_mle", "data", "moving_average",
    "PRESETS", "PointCloud", "Settings", "classify_recording", "iter_frames",
    "process_recording",
    "FormatError", "GeometryError", "MemsStereoError", "NotObservableError", "Recording",
    "System", "acquisition_statistics", "epipolar_pixels", "epipolar_residual",
    "epipolar_segment", "iter_shot_chunks", "load_system", "mirror_normal",
    "phase_from_zero_crossings", "pixels_to_rays", "preset", "project_points",
    "read_recording", "receiver_rays", "reflect", "save_system", "scan_angles",
    "scan_direction", "shot_pixels", "system_from_dict", "system_to_dict", "theta0_exact",
    "theta0_small_angle", "triangulate_midpoint", "write_recording",
]
