"""Checks and attribute order shared by the point cloud writers and readers."""

from __future__ import annotations

from pathlib import Path

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import REQUIRED_ATTRIBUTES, PointCloud


def check_cloud(cloud, path: Path) -> None:
    if not isinstance(cloud, PointCloud):
        raise FormatError("expected a mems_stereo.pipeline.cloud.PointCloud, found "
                          f"{type(cloud).__name__}",
                          source=str(path))


def ordered_attributes(attrs: dict) -> dict:
    """The required attributes first (in their order), then the others sorted."""
    keys = [k for k in REQUIRED_ATTRIBUTES if k in attrs]
    keys += sorted(k for k in attrs if k not in keys)
    return {k: attrs[k] for k in keys}
