"""ROS 2 bags (MCAP or SQLite storage, through the pure-Python ``rosbags``) holding
``sensor_msgs/msg/PointCloud2`` messages with every attribute as a field.

The message's ``header.stamp`` (and the bag's log time) is the cloud's time,
never the time of export: :func:`recording_stamp_ns` gives a recording's (its
shot clock at the first shot: FORMAT v1 keeps shot times in seconds from the
recording's own zero and no wall-clock start, so the stamp is that clock, from
the Unix epoch), :func:`parse_stamp` the time a user gives (``--stamp``: ISO
8601 with a time zone, seconds since the Unix epoch, or ``now``), and
:func:`read_ros2_stamp` a bag's own.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import shutil
import tempfile
import time
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np
from mems_stereo.viz.cloud_common import check_cloud, ordered_attributes

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io import hdf5 as h5
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


def parse_stamp(text: str, option: str = "--stamp") -> int:
    """A time given by a user → ns since the Unix epoch (int).

    ``now`` (the current time), seconds since the epoch (``1764230400``,
    ``1764230400.25``) or ISO 8601 with a time zone (``2026-11-27T08:00:00Z``,
    ``2026-11-27T09:00:00.5+01:00``).  A time without a zone, before 1970 or
    beyond 2262 (int64 ns) raises :class:`~mems_stereo.errors.OptionError`
    naming ``option``.
    """
    t = str(text).strip()
    if t.lower() == "now":
        return time.time_ns()
    try:  # exact decimal seconds: 1764230400.25 → ...250000000 ns, no float rounding
        ns = Decimal(t) * 10**9 if Decimal(t).is_finite() else None
    except InvalidOperation:
        ns = _iso_ns(t, option)
    if ns is None or not 0 <= ns < Decimal(2**63 - 1):
        raise OptionError(f"expected a time from 1970 to 2262, found {text!r}", field=option)
    return int(ns.to_integral_value())


def _iso_ns(t: str, option: str) -> Decimal:
    """ISO 8601 text with a time zone → ns since the Unix epoch (exact)."""
    try:
        d = _dt.datetime.fromisoformat(t.replace("z", "Z"))
    except ValueError:
        d = None
    if d is None:
        raise OptionError(f"expected ISO 8601 (2026-11-27T08:00:00Z), seconds since "
                          f"1970-01-01 UTC or 'now', found {t!r}", field=option)
    if d.tzinfo is None:
        raise OptionError(f"expected a time zone in {t!r} (Z for UTC, or +hh:mm)",
                          field=option)
    dt = d - _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)
    return Decimal((dt.days * 86400 + dt.seconds) * 10**9 + dt.microseconds * 1000)


def recording_stamp_ns(path: str | os.PathLike) -> int:
    """A recording's time (ns, from the Unix epoch): its shot clock at the first shot,
    ``/shots/time[0]`` (line-sensor and two-axis recordings alike); 0 without shots.

    FORMAT v1 stores shot times in seconds from the recording's own zero (no
    wall-clock start), so this is that clock; a negative first shot time raises
    FormatError (a ROS time cannot be negative: give ``--stamp``).
    """
    source = str(path)
    with h5.open_h5(path) as f:
        ds = h5.dataset(f, "/shots/time", source)
        if ds.ndim != 1 or ds.dtype.kind != "f":
            raise FormatError(f"expected (K,) float64 seconds, found {ds.shape} {ds.dtype}",
                              source, "/shots/time")
        t0 = float(ds[0]) if ds.shape[0] else 0.0
    if not (math.isfinite(t0) and t0 >= 0.0):
        raise FormatError(f"first shot time {t0!r} s has no ROS time (negative): give --stamp",
                          source, "/shots/time")
    return int(round(t0 * 1e9))


def is_bag_name(path: str | os.PathLike) -> bool:
    """The name ends in ``.mcap`` or ``.db3`` (a ROS 2 bag output)."""
    return Path(path).suffix.lower() in _ROS_STORAGE


def check_stamp_option(output: str | os.PathLike, stamp: str | None,
                       option: str = "--stamp") -> None:
    """Refuse a ``--stamp`` that is no time (:func:`parse_stamp`) or that has no ROS 2
    bag to stamp (``output`` not ``.mcap``/``.db3``)."""
    if stamp is None:
        return
    if not is_bag_name(output):
        raise OptionError("stamps a ROS 2 bag only (-o .mcap or .db3)", field=option)
    parse_stamp(stamp, option)


def cloud_stamp_ns(output: str | os.PathLike, stamp: str | None, recording) -> int | None:
    """The stamp of a cloud written to ``output`` from ``recording``: None unless
    ``output`` is a ROS 2 bag; else ``stamp`` (:func:`parse_stamp`; the ``--stamp``
    text) or, without it, :func:`recording_stamp_ns` of ``recording``."""
    if not is_bag_name(output):
        return None
    return parse_stamp(stamp) if stamp is not None else recording_stamp_ns(recording)


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


def pointcloud2_message(typestore, cloud: PointCloud, stamp_ns: int,
                        frame_id: str = ROS_FRAME_ID, path: Path | None = None):
    """A ``sensor_msgs/msg/PointCloud2`` of ``cloud`` (``typestore``: rosbags' ROS 2
    Humble types) stamped ``stamp_ns`` (ns since the Unix epoch): x, y, z FLOAT32 m,
    each attribute a field of its own type; ``path`` names the output in errors."""
    where = path if path is not None else Path("<bag>")
    names = ["x", "y", "z"]
    cols = [cloud.points[:, i].astype(np.float32) for i in range(3)]
    for k, v in cloud.attributes.items():
        if k in ("x", "y", "z"):
            raise FormatError(f"attribute name {k!r} is reserved", str(where), k)
        names.append(k)
        cols.append(_ros_field_values(k, v, where))
    dt = np.dtype({"names": names, "formats": [c.dtype.newbyteorder("<") for c in cols]})
    rec = np.empty(len(cloud), dtype=dt)
    for n, c in zip(names, cols):
        rec[n] = c
    T = typestore.types
    stamp = int(stamp_ns)
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
        frame_id=frame_id)
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=int(dt.fields[n][1]),
                                              datatype=_PF[str(dt.fields[n][0].newbyteorder("="))],
                                              count=1) for n in names]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(cloud), fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=dt.itemsize * len(cloud),
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=bool(np.isfinite(cloud.points).all()))


def pointcloud2_to_cloud(m) -> PointCloud:
    """The :class:`PointCloud` of a deserialised PointCloud2 ``m``: x, y, z float64 of its
    fields, every other field an attribute in its own type (native byte order)."""
    dt = np.dtype({"names": [f.name for f in m.fields],
                   "formats": [_PF_DTYPE[f.datatype].newbyteorder(
                       ">" if m.is_bigendian else "<") for f in m.fields],
                   "offsets": [f.offset for f in m.fields], "itemsize": m.point_step})
    a = np.frombuffer(np.asarray(m.data, np.uint8).tobytes(), dtype=dt,
                      count=m.width * m.height)
    pts = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float64)
    attrs = {n: a[n].astype(a[n].dtype.newbyteorder("=")) for n in dt.names
             if n not in ("x", "y", "z")}
    return PointCloud(pts, attrs)


def write_ros2_bag(path: str | os.PathLike, cloud: PointCloud, *, frame_id: str = ROS_FRAME_ID,
                   topic: str = ROS_TOPIC, stamp_ns: int | None = None) -> Path:
    """Write ``cloud`` as one sensor_msgs/msg/PointCloud2 message in a ROS 2 bag.

    ``stamp_ns`` : the cloud's time, ns since the Unix epoch (``header.stamp``
    and the bag's log time; :func:`recording_stamp_ns`, :func:`parse_stamp`);
    required: None raises FormatError (a cloud has no time of its own, and the
    time of export is not the cloud's).

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
    if stamp_ns is None or int(stamp_ns) < 0:
        raise FormatError(f"a ROS 2 bag needs the cloud's time: expected stamp_ns >= 0 (ns "
                          f"since 1970-01-01 UTC), found {stamp_ns!r}", str(p), "stamp")
    bag = ros2_bag_dir(p)
    if bag.exists() and not (bag / "metadata.yaml").is_file():
        raise FormatError("exists and is not a ROS 2 bag; not replacing it", str(bag))
    ts = get_typestore(Stores.ROS2_HUMBLE)
    stamp = int(stamp_ns)
    msg = pointcloud2_message(ts, cloud, stamp, frame_id, p)
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


def read_ros2_stamp(path: str | os.PathLike) -> int | None:
    """The ``header.stamp`` (ns) of a bag's first PointCloud2 message; None without one."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag = ros2_bag_dir(path)
    if not (bag / "metadata.yaml").is_file():
        raise FormatError("not a ROS 2 bag (no metadata.yaml)", str(bag))
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(bag) as r:
        conns = [c for c in r.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"]
        for conn, _, raw in r.messages(connections=conns):
            st = ts.deserialize_cdr(raw, conn.msgtype).header.stamp
            return int(st.sec) * 10**9 + int(st.nanosec)
    return None


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
            c = pointcloud2_to_cloud(ts.deserialize_cdr(raw, conn.msgtype))
            clouds.append(PointCloud(c.points, ordered_attributes(c.attributes)))
    if not clouds:
        raise FormatError("no sensor_msgs/msg/PointCloud2 messages"
                          + (f" on {topic}" if topic else ""), str(bag))
    if len(clouds) == 1:
        return clouds[0]
    c = PointCloud.concatenate(clouds)
    return PointCloud(c.points, ordered_attributes(c.attributes))
