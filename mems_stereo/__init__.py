"""mems-stereo: calibration, dtof triangulation and point clouds for MEMS-scanning SPAD lidar.

The scanner and the SPAD receiver form a projector–camera stereo pair
(Burkard et al., J. Optical Microsystems 2(1), 011005, 2022).  Free functions
on NumPy arrays, one module per concept:

* :mod:`mems_stereo.system`      system description (FORMAT v1), presets
* :mod:`mems_stereo.scanner`     MEMS trajectory, zero crossings → θ, reflection law
* :mod:`mems_stereo.camera`      OpenCV receiver model: pixel ↔ ray
* :mod:`mems_stereo.epipolar`    epipolar residual, readout segment, midpoint triangulation
* :mod:`mems_stereo.acquisition` shots over angle and pixels (paper Sec. 2.1)
* :mod:`mems_stereo.recording`   HDF5 recordings (FORMAT v1), chunked reading and writing
* :mod:`mems_stereo.triangulation`, :mod:`mems_stereo.uncertainty`  dtof triangulation, propagation
* :mod:`mems_stereo.classify`, :mod:`mems_stereo.fastpath`  consistency test; its compiled form
* :mod:`mems_stereo.histogram`, :mod:`mems_stereo.peaks`, :mod:`mems_stereo.points`  histograms,
  background, peaks, fused points
* :mod:`mems_stereo.pipeline`, :mod:`mems_stereo.distributed`  streamed processing; Dask
* :mod:`mems_stereo.timetags`    the same stage for TCSPC time tags
* :mod:`mems_stereo.sim`         the simulator

Frames, units and angles: ``docs/conventions.md``.  The core never imports
Open3D or matplotlib; those load in :mod:`viz` only.
"""

from .acquisition import acquisition_statistics, shot_pixels
from .camera import pixels_to_rays, project_points, receiver_rays
from .epipolar import epipolar_pixels, epipolar_residual, epipolar_segment, triangulate_midpoint
from .errors import FormatError, GeometryError, MemsStereoError, NotObservableError
from .histogram import accumulate_histograms, background_rate_mle, moving_average
from .recording import Recording, iter_shot_chunks, read_recording, write_recording
from .scanner import (
    mirror_normal,
    phase_from_zero_crossings,
    reflect,
    scan_angles,
    scan_direction,
    theta0_exact,
    theta0_small_angle,
)
from .system import System, load_system, preset, save_system, system_from_dict, system_to_dict

__version__ = "0.1.0"

__all__ = [
    "accumulate_histograms", "background_rate_mle", "moving_average",
    "FormatError", "GeometryError", "MemsStereoError", "NotObservableError", "Recording",
    "System", "acquisition_statistics", "epipolar_pixels", "epipolar_residual",
    "epipolar_segment", "iter_shot_chunks", "load_system", "mirror_normal",
    "phase_from_zero_crossings", "pixels_to_rays", "preset", "project_points",
    "read_recording", "receiver_rays", "reflect", "save_system", "scan_angles",
    "scan_direction", "shot_pixels", "system_from_dict", "system_to_dict", "theta0_exact",
    "theta0_small_angle", "triangulate_midpoint", "write_recording",
]
