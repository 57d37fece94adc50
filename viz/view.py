"""Interactive point cloud viewer (Open3D ``draw_geometries``); needs a display."""

from __future__ import annotations

import os
import sys

import numpy as np
from mems_stereo.viz.colormap import cloud_colors

from mems_stereo.errors import MemsStereoError
from mems_stereo.pipeline.cloud import PointCloud


class DisplayUnavailableError(MemsStereoError):
    """No display to open an interactive window on."""


def has_display() -> bool:
    """True when a window can be opened: X11/Wayland on Linux, always elsewhere."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view_cloud(cloud: PointCloud, color_by: str = "range", cmap: str = "turbo",
               vmin: float | None = None, vmax: float | None = None,
               point_size: float = 2.0, window_name: str = "mems-stereo",
               show_axes: bool = True) -> None:
    """Open an interactive window showing ``cloud`` coloured by an attribute; blocks.

    ``color_by``: ``range``, ``counts``, ``sigma_r``, ... or x/y/z.  A 0.1 m
    coordinate frame marks the receiver's projection centre (x red, y green,
    z blue).  Raises DisplayUnavailableError with no display (use
    :func:`mems_stereo.viz.render.render_cloud` for a PNG instead).
    """
    colors = cloud_colors(cloud, color_by, cmap, vmin, vmax)
    if not has_display():
        raise DisplayUnavailableError(
            "no display (DISPLAY and WAYLAND_DISPLAY are unset), so no interactive window can "
            "open; render a PNG with `mems-stereo render CLOUD -o view.png`, or run over "
            "`ssh -X` / under `xvfb-run`")
    import open3d as o3d

    keep = np.isfinite(cloud.points).all(axis=1)
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(cloud.points[keep]))
    pc.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(colors[keep]))
    geoms = [pc]
    if show_axes:
        geoms.append(o3d.geometry.TriangleMesh.create_coordinate_frame(size=0.1))
    vis = o3d.visualization.Visualizer()
    if not vis.create_window(window_name=window_name, width=1280, height=960):
        raise DisplayUnavailableError("Open3D could not open a window on the display")
    try:
        for g in geoms:
            vis.add_geometry(g)
        vis.get_render_option().point_size = float(point_size)
        # start at the receiver's viewpoint: OpenCV camera at the origin looking along +z
        vc = vis.get_view_control()
        vc.set_front([0.0, 0.0, -1.0])
        vc.set_up([0.0, -1.0, 0.0])
        if len(pc.points):
            vc.set_lookat(np.asarray(pc.get_center()))
        vis.run()
    finally:
        vis.destroy_window()
