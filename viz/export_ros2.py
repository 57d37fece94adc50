"""ROS 2 bags (MCAP or SQLite storage, through the pure-Python ``rosbags``) holding
``sensor_msgs/msg/PointCloud2`` messages with every attribute as a field."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from mems_stereo.viz.cloud_common import check_cloud, ordered_attributes

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud

#: ROS 2 bag defaults: the receiver camera frame is an optical frame (x right, y down,
#: z forward), as ROS names frames with the OpenCV convention
ROS_FRAME_ID = "mems_stereo_receiver_optical_frame"
ROS_TOPIC = "/mems_stereo/points"
_ROS_STORAGE = {".mcap": "MCAP", ".db3": "SQLITE3"}
# PointField datatypes (sensor_msgs/msg/PointField constants)
_PF = {"int8": 1, "uint8": 2, "int16": 3, "uint16": 4, "int32": 5, "uint32": 6,
       "float32": 7, "float64": 8}
_PF_DTYPE = {v: np.dtype(k) for k, v in _PF.items()}


def ros2_bag_dir(path: str | os.PathLike) -> Path:
    """The rosbag2 directory of an output name: ``room.mcap`` → ``room/`` (which holds
    ``room.mcap`` and ``metadata.yaml``, as ``ros2 bag record -o room -s mcap`` makes)."""
    p = Path(path)
    return p.with_suffix("") if p.suffix.lower() in _ROS_STORAGE else p


def _ros_field_values(name: str, v: np.ndarray, path: Path) -> np.ndarray:
    v = np.asarray(v)
    if v.dtype == np.bool_:
        return v.astype(np.uint8)
    if v.dtype == np.float16:
        return v.astype(np.float32)
    if str(v.dtype) in _PF:
        return v
    if v.dtype.kind in "iu":  # 64-bit integers: PointField has none
        for t in ("int32", "uint32"):
            info = np.iinfo(t)
            if v.size == 0 or (int(v.min()) >= info.min and int(v.max()) <= info.max):
                return v.astype(t)
    raise FormatError(f"attribute {name!r} ({v.dtype}) has no sensor_msgs/PointField type",
                      source=str(path), field=name)


def write_ros2_bag(path: str | os.PathLike, cloud: PointCloud, *, frame_id: str = ROS_FRAME_ID,
                   topic: str = ROS_TOPIC, stamp_ns: int | None = None) -> Path:
    """Write ``cloud`` as one sensor_msgs/msg/PointCloud2 message in a ROS 2 bag.

    ``path`` ending in ``.mcap`` (MCAP storage) or ``.db3`` (SQLite 3) names
    the bag: the directory :func:`ros2_bag_dir` is created (replaced when it
    holds a bag).  Fields: ``x, y, z`` FLOAT32 (metres, the receiver camera
    frame = ``frame_id``, an optical frame; float32 as RViz and PCL expect:
    < 1 µm at 10 m) and one field per attribute in its own type (int64 →
    INT32/UINT32 when the values fit; bool → UINT8).  ``height`` 1, ``width``
    N, little endian, ``is_dense`` when every point is finite.  Written through
    the pure-Python ``rosbags`` (ROS 2 Humble message definitions); returns the
    bag directory.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    sfx = p.suffix.lower()
    if sfx not in _ROS_STORAGE:
        raise FormatError(f"expected a .mcap or .db3 bag name, found {p.name!r}", str(p))
    check_cloud(cloud, p)
    bag = ros2_bag_dir(p)
    if bag.exists() and not (bag / "metadata.yaml").is_file():
        raise FormatError("exists and is not a ROS 2 bag; not replacing it", str(bag))
    names = ["x", "y", "z"]
    cols = [cloud.points[:, i].astype(np.float32) for i in range(3)]
    for k, v in cloud.attributes.items():
        if k in ("x", "y", "z"):
            raise FormatError(f"attribute name {k!r} is reserved", str(p), k)
        names.append(k)
        cols.append(_ros_field_values(k, v, p))
    dt = np.dtype({"names": names, "formats": [c.dtype.newbyteorder("<") for c in cols]})
    rec = np.empty(len(cloud), dtype=dt)
    for n, c in zip(names, cols):
        rec[n] = c
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    stamp = time.time_ns() if stamp_ns is None else int(stamp_ns)
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
        frame_id=frame_id)
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=int(dt.fields[n][1]),
                                              datatype=_PF[str(dt.fields[n][0].newbyteorder("="))],
                                              count=1) for n in names]
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(cloud), fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=dt.itemsize * len(cloud),
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=bool(np.isfinite(cloud.points).all()))
    raw = ts.serialize_cdr(msg, msg.__msgtype__)
    bag.parent.mkdir(parents=True, exist_ok=True)
    tmp_parent = Path(tempfile.mkdtemp(prefix=f".{bag.name}.", suffix=".part", dir=bag.parent))
    try:
        w = Writer(tmp_parent / bag.name, version=8,
                   storage_plugin=getattr(StoragePlugin, _ROS_STORAGE[sfx]))
        w.open()
        try:
            conn = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(conn, stamp, raw)
        finally:
            w.close()
        if bag.exists():
            shutil.rmtree(bag)
        os.replace(tmp_parent / bag.name, bag)
    finally:
        shutil.rmtree(tmp_parent, ignore_errors=True)
    return bag


def read_ros2_bag(path: str | os.PathLike, topic: str | None = None) -> PointCloud:
    """Read the PointCloud2 messages of a ROS 2 bag (directory, or the ``.mcap``/``.db3``
    name given to :func:`write_ros2_bag`) into one :class:`PointCloud`.

    Every field becomes an attribute (x, y, z the points, float64); messages
    of ``topic`` (default: every PointCloud2 topic) are concatenated.
    """
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag = ros2_bag_dir(path)
    if not (bag / "metadata.yaml").is_file():
        if not Path(path).exists() and not bag.exists():
            raise FileNotFoundError(2, "file not found", str(path))
        raise FormatError("not a ROS 2 bag (no metadata.yaml)", str(bag))
    ts = get_typestore(Stores.ROS2_HUMBLE)
    clouds = []
    with Reader(bag) as r:
        conns = [c for c in r.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"
                 and (topic is None or c.topic == topic)]
        for conn, _, raw in r.messages(connections=conns):
            m = ts.deserialize_cdr(raw, conn.msgtype)
            dt = np.dtype({"names": [f.name for f in m.fields],
                           "formats": [_PF_DTYPE[f.datatype].newbyteorder(
                               ">" if m.is_bigendian else "<") for f in m.fields],
                           "offsets": [f.offset for f in m.fields], "itemsize": m.point_step})
            a = np.frombuffer(np.asarray(m.data, np.uint8).tobytes(), dtype=dt,
                              count=m.width * m.height)
            pts = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float64)
            attrs = {n: a[n].astype(a[n].dtype.newbyteorder("=")) for n in dt.names
                     if n not in ("x", "y", "z")}
            clouds.append(PointCloud(pts, ordered_attributes(attrs)))
    if not clouds:
        raise FormatError("no sensor_msgs/msg/PointCloud2 messages"
                          + (f" on {topic}" if topic else ""), str(bag))
    if len(clouds) == 1:
        return clouds[0]
    c = PointCloud.concatenate(clouds)
    return PointCloud(c.points, ordered_attributes(c.attributes))
