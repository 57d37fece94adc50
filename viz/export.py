"""Point cloud files: PLY written with NumPy, PCD through Open3D tensor clouds, LAS through laspy.

:func:`write_cloud` / :func:`read_cloud` pick the format from the extension.

* ``.ply`` (binary little endian) and ``.pcd`` (binary): ``x, y, z`` float64
  metres in the world (receiver camera) frame and one scalar property per
  attribute of the :class:`~mems_stereo.pipeline.cloud.PointCloud` (PCD: an
  (N, 1) tensor attribute of an ``open3d.t.geometry.PointCloud``; PLY: the
  same properties and types written by NumPy, in the cloud's attribute order,
  so writing a PLY does not import Open3D).  Both are read through Open3D.  Round trips
  are exact (values and dtypes) for float32/64, int32, uint8 and uint16; PCD
  also keeps int64.  Other dtypes are converted losslessly before writing
  (bool → uint8, int8/int16 → int32, float16 → float32, int64/uint32 → int32
  in PLY when every value fits) or refused with :class:`FormatError`.
* ``.las`` (LAS 1.4, point format 6, through laspy): x, y, z stored as int32
  with scale :data:`LAS_SCALE` = 0.1 mm and an offset at the cloud's minimum,
  so coordinates come back within ``LAS_SCALE / 2`` = 0.05 mm; every attribute
  is an "extra bytes" dimension of its own dtype and comes back exactly.
  ``intensity`` carries ``counts`` clipped to 0..65535 for other lidar tools.
  ``.laz`` (LAZ compression) works out of the box: ``lazrs`` is a dependency.
* ``.mcap`` / ``.db3``: a ROS 2 bag (MCAP or SQLite storage, through the
  pure-Python ``rosbags``) holding one ``sensor_msgs/msg/PointCloud2`` with
  every attribute as a field; ``room.mcap`` names the bag directory ``room/``
  (:func:`write_ros2_bag`).

Writes are atomic (:func:`mems_stereo.util.atomic.atomic_output`).  Files
written here are read back by any PLY/PCD/LAS tool (CloudCompare, PDAL).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mems_stereo.viz.cloud_common import check_cloud, ordered_attributes
from mems_stereo.viz.export_las import LAS_SCALE, read_las, write_las  # noqa: F401
from mems_stereo.viz.export_ros2 import (  # noqa: F401  (public names re-exported)
    ROS_FRAME_ID,
    ROS_TOPIC,
    read_ros2_bag,
    ros2_bag_dir,
    write_ros2_bag,
)

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.util.atomic import atomic_output
from mems_stereo.util.limits import check_allocation
from mems_stereo.util.paths import require_input_file

FORMATS = (".ply", ".pcd", ".las", ".laz", ".mcap", ".db3")

# dtypes Open3D keeps exactly as (N, 1) attributes (ENVIRONMENT.md)
_PLY_DTYPES = {np.dtype(t) for t in ("float32", "float64", "int32", "uint8", "uint16")}
_PCD_DTYPES = _PLY_DTYPES | {np.dtype("int64")}
# names an Open3D tensor cloud uses for its own data
_O3D_RESERVED = {"positions", "colors", "normals"}


def _suffix(path: Path) -> str:
    sfx = path.suffix.lower()
    if sfx not in FORMATS:
        raise FormatError(f"unknown point cloud extension {path.suffix!r}; expected one of "
                          f"{', '.join(FORMATS)}", source=str(path))
    return sfx


def _storable(name: str, values: np.ndarray, allowed: set, path: Path) -> np.ndarray:
    """Convert an attribute losslessly to a dtype the format keeps, or raise."""
    v = np.asarray(values)
    if v.dtype in allowed:
        return v
    if v.dtype == np.bool_:
        return v.astype(np.uint8)
    if v.dtype == np.float16:
        return v.astype(np.float32)
    if np.issubdtype(v.dtype, np.integer):
        info = np.iinfo(np.int32)
        if v.size == 0 or (int(v.min()) >= info.min and int(v.max()) <= info.max):
            return v.astype(np.int32)
        raise FormatError(f"attribute {name!r} ({v.dtype}) has values outside int32, which "
                          f"{path.suffix} cannot store; use .pcd", source=str(path), field=name)
    raise FormatError(f"attribute {name!r} has dtype {v.dtype}; expected a numeric dtype",
                      source=str(path), field=name)


def write_cloud(path: str | os.PathLike, cloud: PointCloud, *,
                stamp_ns: int | None = None) -> Path:
    """Write ``cloud`` to ``path`` (.ply, .pcd, .las, .laz) atomically; returns the path.

    ``cloud.points`` : (N, 3) float64, metres, world frame; every attribute
    (N,) is written (see the module docstring for dtypes and precision).
    ``stamp_ns`` : the cloud's time for a ROS 2 bag (.mcap, .db3; required
    there, see :func:`~mems_stereo.viz.export_ros2.write_ros2_bag`); unused otherwise.
    """
    path = Path(path)
    sfx = _suffix(path)
    check_cloud(cloud, path)
    if path.exists() and path.is_dir():
        raise FormatError("is a directory, expected a file", source=str(path))
    if sfx in (".ply", ".pcd"):
        allowed = _PLY_DTYPES if sfx == ".ply" else _PCD_DTYPES
        attrs = {}
        for k, v in cloud.attributes.items():
            if k in _O3D_RESERVED or k in ("x", "y", "z"):
                raise FormatError(f"attribute name {k!r} is reserved in {sfx}",
                                  source=str(path), field=k)
            attrs[k] = _storable(k, v, allowed, path)
        with atomic_output(path) as tmp:
            if sfx == ".ply":
                _write_ply(tmp, cloud.points, attrs)
            elif len(cloud) == 0:
                _write_empty_header(tmp, sfx, attrs)
            else:
                _write_o3d(tmp, cloud.points, attrs)
    elif sfx in (".mcap", ".db3"):
        return write_ros2_bag(path, cloud, stamp_ns=stamp_ns)
    else:
        write_las(path, cloud)
    return path


def _ply_header(n: int, names: list, dtypes: list) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", "comment Created by mems-stereo",
             f"element vertex {n}"]
    lines += [f"property {_PLY_TYPE[d]} {k}" for k, d in zip(names, dtypes)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _write_ply(tmp: Path, points: np.ndarray, attrs: dict) -> None:
    """Binary little-endian PLY written with NumPy (no Open3D import: it would
    dominate a short run's start-up).  The properties and their types are those Open3D
    writes (``x, y, z`` double, then one scalar property per attribute, in the
    cloud's order); Open3D, CloudCompare and PDAL read it."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    names = ["x", "y", "z", *attrs]
    dtypes = ["float64"] * 3 + [str(v.dtype) for v in attrs.values()]
    rec = np.empty(len(pts), dtype=np.dtype({"names": names, "formats": [
        np.dtype(d).newbyteorder("<") for d in dtypes]}))
    for i, axis in enumerate("xyz"):
        rec[axis] = pts[:, i]
    for k, v in attrs.items():
        rec[k] = v.reshape(-1)
    with open(tmp, "wb") as f:
        f.write(_ply_header(len(pts), names, dtypes))
        f.write(rec.tobytes())


def _write_o3d(tmp: Path, points: np.ndarray, attrs: dict) -> None:
    import open3d as o3d

    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points, np.float64)))
    for k, v in attrs.items():
        pc.point[k] = o3d.core.Tensor(np.ascontiguousarray(v.reshape(-1, 1)))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.t.io.write_point_cloud(str(tmp), pc, write_ascii=False, compressed=False)
    if not ok:
        raise FormatError("Open3D could not write the point cloud", source=str(tmp))


_PLY_TYPE = {"float64": "double", "float32": "float", "int32": "int", "uint8": "uchar",
             "uint16": "uint16"}
_PCD_TYPE = {"float64": ("8", "F"), "float32": ("4", "F"), "int32": ("4", "I"),
             "uint8": ("1", "U"), "uint16": ("2", "U"), "int64": ("8", "I")}


def _write_empty_header(tmp: Path, sfx: str, attrs: dict) -> None:
    """Open3D refuses to write 0 points; a header-only file is still a valid cloud (PCD)."""
    names = ["x", "y", "z", *attrs]
    dtypes = ["float64"] * 3 + [str(v.dtype) for v in attrs.values()]
    if sfx == ".ply":
        tmp.write_bytes(_ply_header(0, names, dtypes))
        return
    lines = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
             "FIELDS " + " ".join(names),
             "SIZE " + " ".join(_PCD_TYPE[d][0] for d in dtypes),
             "TYPE " + " ".join(_PCD_TYPE[d][1] for d in dtypes),
             "COUNT " + " ".join("1" for _ in names), "WIDTH 0", "HEIGHT 1",
             "VIEWPOINT 0 0 0 1 0 0 0", "POINTS 0", "DATA binary"]
    tmp.write_bytes(("\n".join(lines) + "\n").encode("ascii"))


def _empty_pcd(path: Path) -> PointCloud | None:
    """Parse a header-only PCD (Open3D cannot read one); None if not such a file."""
    rev = {v: k for k, v in _PCD_TYPE.items()}
    head = {}
    with open(path, "rb") as f:
        for _ in range(20):
            line = f.readline().decode("ascii", "replace").strip()
            if not line or line.startswith("#"):
                continue
            key, _, rest = line.partition(" ")
            head[key] = rest.split()
            if key == "DATA":
                break
    if head.get("POINTS") != ["0"] or "FIELDS" not in head:
        return None
    attrs = {}
    for n, s, t in zip(head["FIELDS"], head.get("SIZE", []), head.get("TYPE", [])):
        if n not in ("x", "y", "z") and (s, t) in rev:
            attrs[n] = np.zeros(0, dtype=rev[(s, t)])
    return PointCloud(np.zeros((0, 3)), attrs)


def read_cloud(path: str | os.PathLike) -> PointCloud:
    """Read a .ply, .pcd, .las or .laz point cloud into a :class:`PointCloud`.

    Points come back (N, 3) float64 metres; each scalar per-point property
    becomes an (N,) attribute with its stored dtype.  Multi-channel properties
    of foreign files (colours, normals) are left out.  Raises FormatError for
    an unknown extension or an unreadable file, FileNotFoundError when missing.
    """
    path = Path(path)
    sfx = _suffix(path)
    if sfx in (".mcap", ".db3"):
        return read_ros2_bag(path)
    require_input_file(path)
    if sfx in (".las", ".laz"):
        return read_las(path)
    if sfx == ".ply":
        _check_ply_header(path)
    else:
        _check_pcd_header(path)
    import open3d as o3d

    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pc = o3d.t.io.read_point_cloud(str(path))
    except (RuntimeError, ValueError, OSError) as e:
        raise FormatError(f"not a readable {sfx[1:].upper()} point cloud ({str(e)[:120]})",
                          source=str(path)) from None
    if "positions" not in pc.point:
        if sfx == ".pcd":
            empty = _empty_pcd(path)
            if empty is not None:
                return empty
        raise FormatError(f"not a readable {sfx[1:].upper()} point cloud (Open3D found no "
                          "points in it)", source=str(path))
    points = pc.point.positions.numpy().astype(np.float64)
    attrs = {}
    for k in pc.point:
        if k in _O3D_RESERVED:
            continue
        a = pc.point[k].numpy()
        if a.ndim == 2 and a.shape[1] == 1:
            attrs[k] = a[:, 0].copy()
    return PointCloud(points, ordered_attributes(attrs))


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
              "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
              "float": 4, "float32": 4, "double": 8, "float64": 8}
_MAX_HEADER = 1 << 16


def _read_header_lines(path: Path, end: str, limit: int = 4096) -> tuple[list[str], int]:
    """ASCII header lines up to and including ``end`` and the header's byte length."""
    lines, n = [], 0
    with open(path, "rb") as f:
        for _ in range(limit):
            raw = f.readline(_MAX_HEADER)
            if not raw:
                break
            n += len(raw)
            line = raw.decode("ascii", "replace").strip()
            lines.append(line)
            if line.split(" ", 1)[0] == end:
                return lines, n
    raise FormatError(f"no '{end}' line in the header: not a point cloud or truncated",
                      source=str(path))


@dataclass
class PlyElement:
    """One ``element`` of a PLY header, filled while the header is parsed.

    name, n : the element's name and declared count; props : its property
    names in order; size : bytes per row of its scalar properties;
    has_list : whether a ``property list`` makes its rows variable-sized.
    """

    name: str
    n: int
    props: list[str] = field(default_factory=list)
    size: int = 0
    has_list: bool = False


def _parse_ply_elements(lines: list[str], path: Path) -> tuple[str | None, list[PlyElement]]:
    """The format (``ascii``, ``binary_little_endian``, ...) and the elements of a PLY
    header's lines (without the first, ``ply``)."""
    fmt, elements, cur = None, [], None
    for ln in lines:
        w = ln.split()
        if not w:
            continue
        if w[0] == "format" and len(w) >= 2:
            fmt = w[1]
        elif w[0] == "element" and len(w) == 3:
            try:
                n = int(w[2])
            except ValueError:
                raise FormatError(f"element {w[1]}: expected a count, found {w[2]!r}",
                                  source=str(path)) from None
            if n < 0:
                raise FormatError(f"element {w[1]}: negative count {n}", source=str(path))
            cur = PlyElement(w[1], n)
            elements.append(cur)
        elif w[0] == "property" and cur is not None:
            if len(w) >= 2 and w[1] == "list":
                cur.has_list = True
                cur.props.append(w[-1])
            elif len(w) == 3 and w[1] in _PLY_SIZES:
                cur.props.append(w[2])
                cur.size += _PLY_SIZES[w[1]]
            else:
                raise FormatError(f"unknown property line {ln!r}", source=str(path))
    return fmt, elements


def _check_ply_data_length(path: Path, fmt: str | None, elements: list[PlyElement],
                           vert: PlyElement, head: int) -> None:
    """Refuse a PLY whose data (after the ``head`` header bytes) are shorter than declared."""
    real = path.stat().st_size - head
    if fmt in ("binary_little_endian", "binary_big_endian"):
        need, exact = 0, True
        for e in elements:
            if e.has_list:
                exact = False
                break
            need += e.n * e.size
        if exact and real < need:
            raise FormatError(f"truncated: the header declares {vert.n} vertices "
                              f"({need} bytes of data), the file holds {real}",
                              source=str(path))
    elif fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(head)
            rows = sum(1 for line in f if line.strip())
        if rows < sum(e.n for e in elements):
            raise FormatError(f"truncated: the header declares {vert.n} vertices, the file "
                              f"holds {rows} data lines", source=str(path))
    else:
        raise FormatError(f"unknown PLY format {fmt!r}", source=str(path))


def _check_ply_header(path: Path) -> None:
    """Refuse a PLY whose header lacks x, y, z or whose data are shorter than declared."""
    lines, head = _read_header_lines(path, "end_header")
    if not lines or lines[0] != "ply":
        raise FormatError("expected a PLY file (first line 'ply')", source=str(path))
    fmt, elements = _parse_ply_elements(lines[1:], path)
    vert = next((e for e in elements if e.name == "vertex"), None)
    if vert is None:
        raise FormatError("no 'element vertex' in the header", source=str(path))
    missing = [c for c in ("x", "y", "z") if c not in vert.props]
    if missing:
        raise FormatError(f"the vertices lack the coordinate(s) {', '.join(missing)}",
                          source=str(path), field="vertex")
    _check_ply_data_length(path, fmt, elements, vert, head)
    check_allocation(vert.n * (24 + 8 * len(vert.props)), f"{vert.n} points", str(path))


def _check_pcd_header(path: Path) -> None:
    """Refuse a PCD without x, y, z or whose binary data are shorter than declared."""
    lines, head = _read_header_lines(path, "DATA")
    h = {}
    for ln in lines:
        if ln and not ln.startswith("#"):
            k, _, rest = ln.partition(" ")
            h[k] = rest.split()
    fields = h.get("FIELDS", [])
    missing = [c for c in ("x", "y", "z") if c not in fields]
    if missing:
        raise FormatError(f"the points lack the field(s) {', '.join(missing)}",
                          source=str(path), field="FIELDS")
    try:
        n = int(h.get("POINTS", ["-1"])[0])
        sizes = [int(x) for x in h.get("SIZE", [])]
        counts = [int(x) for x in h.get("COUNT", ["1"] * len(sizes))]
    except ValueError:
        raise FormatError("expected integer POINTS, SIZE and COUNT", source=str(path)) from None
    if n < 0 or len(sizes) != len(fields) or len(counts) != len(fields):
        raise FormatError("expected POINTS >= 0 and one SIZE and COUNT per field",
                          source=str(path))
    if h.get("DATA", [""])[0] == "binary":
        need = n * sum(s * c for s, c in zip(sizes, counts))
        real = path.stat().st_size - head
        if real < need:
            raise FormatError(f"truncated: the header declares {n} points ({need} bytes of "
                              f"data), the file holds {real}", source=str(path))
    check_allocation(n * (24 + 8 * len(fields)), f"{n} points", str(path))
