"""Conversions of a :class:`~mems_stereo.pipeline.cloud.PointCloud` to other libraries' types."""

from __future__ import annotations

import numpy as np
from mems_stereo.viz.colormap import cloud_colors


def cloud_to_open3d(cloud, color_by: str | None = "range", cmap: str = "turbo",
                    vmin: float | None = None, vmax: float | None = None):
    """``open3d.geometry.PointCloud`` with the points (m) and colours from an attribute.

    color_by : attribute name or ``x``/``y``/``z`` (see
        :func:`~mems_stereo.viz.colormap.cloud_colors`), None for no colours.

    Points with a non-finite coordinate are kept (Open3D ignores them in
    drawing); NaN attribute values get the grey ``NAN_COLOR``.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.ascontiguousarray(cloud.points, np.float64)))
    if color_by is not None and len(cloud):
        rgb = cloud_colors(cloud, color_by, cmap, vmin, vmax)
        pcd.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(rgb, np.float64))
    return pcd
