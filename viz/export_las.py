"""LAS 1.4 / LAZ point clouds through laspy (:func:`mems_stereo.viz.export.write_cloud`).

x, y, z are stored as int32 with scale :data:`LAS_SCALE` = 0.1 mm and an offset at the
cloud's minimum; every attribute is an "extra bytes" dimension of its own dtype;
``intensity`` carries ``counts`` clipped to 0..65535.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mems_stereo.viz.cloud_common import ordered_attributes

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.util.atomic import atomic_output
from mems_stereo.util.limits import check_allocation

#: LAS coordinate resolution, m (quantisation error at most half of it)
LAS_SCALE = 1e-4


def _laspy():
    import laspy

    return laspy


def write_las(path: Path, cloud: PointCloud) -> None:
    laspy = _laspy()
    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise FormatError("writing .laz needs a LAZ backend for laspy (pip install lazrs); "
                          "use .las", source=str(path))
    pts = cloud.points
    if not np.all(np.isfinite(pts)):
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise FormatError(f"{bad} points have non-finite coordinates, which LAS cannot store",
                          source=str(path), field="points")
    header = laspy.LasHeader(point_format=6, version="1.4")
    standard = {d.lower() for d in header.point_format.dimension_names}
    extra = []
    attrs = {}
    for k, v in cloud.attributes.items():
        if k.lower() in standard or len(k) > 32:
            raise FormatError(f"attribute name {k!r} clashes with a LAS dimension or is longer "
                              "than 32 characters", source=str(path), field=k)
        v = np.asarray(v)
        if v.dtype == np.bool_:
            v = v.astype(np.uint8)
        if v.dtype.kind not in "uif" or v.dtype.itemsize > 8 or v.dtype == np.float16:
            raise FormatError(f"attribute {k!r} has dtype {v.dtype}, which LAS extra bytes "
                              "cannot store", source=str(path), field=k)
        attrs[k] = v
        extra.append(laspy.ExtraBytesParams(name=k, type=v.dtype))
    if extra:
        header.add_extra_dims(extra)
    lo = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    header.offsets = lo
    header.scales = np.full(3, LAS_SCALE)
    if len(pts) and (pts.max(axis=0) - lo).max() / LAS_SCALE >= 2**31 - 1:
        raise FormatError(f"the cloud spans more than {(2**31 - 1) * LAS_SCALE:.0f} m, beyond "
                          f"LAS int32 coordinates at {LAS_SCALE} m resolution", source=str(path))
    las = laspy.LasData(header)
    if len(pts):
        las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    else:
        las.points = laspy.ScaleAwarePointRecord.zeros(0, header=header)
    n = len(pts)
    las.return_number = np.ones(n, np.uint8)
    las.number_of_returns = np.ones(n, np.uint8)
    if "counts" in attrs:
        las.intensity = np.clip(attrs["counts"], 0, 65535).astype(np.uint16)
    for k, v in attrs.items():
        las[k] = v
    with atomic_output(path) as tmp:
        las.write(str(tmp))


def read_las(path: Path) -> PointCloud:
    laspy = _laspy()
    try:
        with laspy.open(str(path)) as rd:
            hdr = rd.header
            scales = np.asarray(hdr.scales, dtype=np.float64)
            if scales.shape != (3,) or not np.all(np.isfinite(scales)) or np.any(scales <= 0):
                raise FormatError(f"expected positive finite coordinate scales, found "
                                  f"{scales.tolist()}", source=str(path), field="header.scales")
            offs = np.asarray(hdr.offsets, dtype=np.float64)
            if not np.all(np.isfinite(offs)):
                raise FormatError(f"expected finite offsets, found {offs.tolist()}",
                                  source=str(path), field="header.offsets")
            n = int(hdr.point_count)
            size = hdr.point_format.size
            if path.suffix.lower() == ".las":
                real = path.stat().st_size - int(hdr.offset_to_point_data)
                if real < n * size:
                    raise FormatError(f"truncated: the header declares {n} points "
                                      f"({n * size} bytes), the file holds {max(real, 0)}",
                                      source=str(path))
            check_allocation(n * (size + 48), f"{n} points", str(path))
            las = rd.read()
    except FormatError:
        raise
    except (laspy.errors.LaspyException, ValueError, OSError, EOFError, KeyError,
            IndexError, TypeError) as e:
        raise FormatError(f"not a readable LAS/LAZ file: {str(e)[:120]}", source=str(path)) \
            from None
    points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    attrs = {}
    for name in las.point_format.extra_dimension_names:
        a = np.asarray(las[name])
        if a.ndim == 1:
            attrs[name] = a.copy()
    return PointCloud(points.astype(np.float64), ordered_attributes(attrs))
