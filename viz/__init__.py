"""Point cloud files, Open3D rendering and viewing, matplotlib figures.

* :mod:`mems_stereo.viz.export`   – ``write_cloud`` / ``read_cloud``: .ply, .pcd (Open3D
  tensor clouds), .las
* :mod:`mems_stereo.viz.render`   – ``render_cloud``: headless PNG through Open3D + Mesa EGL
  (what is drawn besides the points: :mod:`mems_stereo.viz.render_decorations`)
* :mod:`mems_stereo.viz.convert`  – ``cloud_to_open3d``: a cloud as an Open3D point cloud
* :mod:`mems_stereo.viz.view`     – ``view_cloud``: interactive Open3D window (needs a display)
* :mod:`mems_stereo.viz.plots`    – the paper's figures with matplotlib (Agg)
* :mod:`mems_stereo.viz.colormap` – NumPy colormaps (no matplotlib)

Importing :mod:`viz` loads neither Open3D nor matplotlib; the names below
load their module on first use.  Formats and the rendering set-up:
``docs/visualisation.md``.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "write_cloud": "export", "read_cloud": "export",
    "render_cloud": "render", "render_image": "render", "Decorations": "render_decorations",
    "view_cloud": "view",
    "plot_acquisition": "plots", "plot_histograms": "plots", "plot_peaks": "plots",
    "plot_uncertainty_bounds": "plots", "plot_calibration_residuals": "plots",
    "plot_cloud_topview": "plots",
    "apply_colormap": "colormap", "cloud_colors": "colormap", "ColorScale": "colormap",
    "write_calibration_report": "calib_report", "write_ros2_bag": "export",
    "cloud_to_open3d": "convert",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
