"""Frame sinks: one cloud file per frame in a folder, or one ROS 2 bag of all frames.

:class:`FrameFolderSink` writes frame i of a recording ``room.h5`` as
``<folder>/room_<i:06d>.ply`` (or ``.pcd``, ``.las``, ``.laz``; each file atomic,
:func:`~mems_stereo.viz.export.write_cloud`); :class:`FrameBagSink` writes one
``sensor_msgs/msg/PointCloud2`` per frame, stamped with the frame's start (the
recording's clock, s → ns), into a ROS 2 bag (``.mcap`` or ``.db3``, through the
pure-Python ``rosbags``), built in a temporary folder beside the target and renamed
over it when the sink closes (the finished frames are kept when the run fails
mid-way).  The fields are those of :func:`~mems_stereo.viz.export.write_ros2_bag`
(``x, y, z`` FLOAT32, every attribute in its own type, ``t`` FLOAT64, ``age`` INT32),
so :func:`read_frames_bag` reads each message back as a
:class:`~mems_stereo.pipeline.cloud.PointCloud`.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from mems_stereo.viz.cloud_common import check_cloud
from mems_stereo.viz.export import write_cloud
from mems_stereo.viz.export_ros2 import (
    ROS_FRAME_ID,
    ROS_TOPIC,
    pointcloud2_message,
    pointcloud2_to_cloud,
    ros2_bag_dir,
)

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud

#: the file formats of a frame folder (``--frame-format``)
FRAME_FORMATS = ("ply", "pcd", "las", "laz")
_ROS_STORAGE = {".mcap": "MCAP", ".db3": "SQLITE3"}


def frame_path(folder, stem: str, index: int, fmt: str = "ply") -> Path:
    """``folder/<stem>_<index:06d>.<fmt>``."""
    return Path(folder) / f"{stem}_{int(index):06d}.{fmt}"


class FrameFolderSink:
    """One cloud file per frame: :meth:`write` returns the path written (atomic)."""

    def __init__(self, folder, stem: str, fmt: str = "ply"):
        if fmt not in FRAME_FORMATS:
            raise FormatError(f"expected a frame format of {', '.join(FRAME_FORMATS)}, found "
                              f"{fmt!r}", field="--frame-format")
        self.folder, self.stem, self.fmt = Path(folder), stem, fmt
        self.written: list[Path] = []

    def write(self, frame) -> Path:
        p = write_cloud(frame_path(self.folder, self.stem, frame.index, self.fmt), frame.cloud)
        self.written.append(p)
        return p

    def close(self) -> None:
        """Nothing to finish (each file is complete when written)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def stamp_of(seconds: float) -> int:
    """Nanoseconds of a time in s (the recording's clock; negative times clipped to 0)."""
    return max(0, int(round(float(seconds) * 1e9)))


class FrameBagSink:
    """A ROS 2 bag (``path`` ending in .mcap or .db3; the bag folder is
    :func:`~mems_stereo.viz.export.ros2_bag_dir` of it) of one PointCloud2 per frame."""

    def __init__(self, path, *, topic: str = ROS_TOPIC, frame_id: str = ROS_FRAME_ID):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        p = Path(path)
        sfx = p.suffix.lower()
        if sfx not in _ROS_STORAGE:
            raise FormatError(f"expected a .mcap or .db3 bag name, found {p.name!r}", str(p))
        self.path, self.bag = p, ros2_bag_dir(p)
        if self.bag.exists() and not (self.bag / "metadata.yaml").is_file():
            raise FormatError("exists and is not a ROS 2 bag; not replacing it", str(self.bag))
        self.frame_id, self.n = frame_id, 0
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.bag.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.bag.name}.", suffix=".part",
                                         dir=self.bag.parent))
        self.writer = Writer(self.tmp / self.bag.name, version=8,
                             storage_plugin=getattr(StoragePlugin, _ROS_STORAGE[sfx]))
        self.writer.open()
        msgtype = "sensor_msgs/msg/PointCloud2"
        self.conn = self.writer.add_connection(topic, msgtype, typestore=self.ts)

    def write(self, frame) -> Path:
        """Add one frame's cloud, stamped with ``frame.start``."""
        check_cloud(frame.cloud, self.path)
        stamp = stamp_of(frame.start)
        msg = pointcloud2_message(self.ts, frame.cloud, stamp, self.frame_id, self.path)
        self.writer.write(self.conn, stamp, self.ts.serialize_cdr(msg, msg.__msgtype__))
        self.n += 1
        return self.bag

    def close(self) -> Path:
        """Finish the bag and move it over the target folder."""
        if self.writer is not None:
            try:
                self.writer.close()
                if self.bag.exists():
                    shutil.rmtree(self.bag)
                os.replace(self.tmp / self.bag.name, self.bag)
            finally:
                self.writer = None
                shutil.rmtree(self.tmp, ignore_errors=True)
        return self.bag

    def abort(self) -> None:
        """Discard the bag (the target is left as it was)."""
        if self.writer is not None:
            try:
                self.writer.close()
            finally:
                self.writer = None
                shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        """Close on success; on an error discard the bag (call :meth:`close` first to keep
        the finished frames, e.g. on Ctrl-C)."""
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def open_frame_sink(out, stem: str, fmt: str = "ply"):
    """The sink of an output: a .mcap/.db3 name → :class:`FrameBagSink`, else a folder →
    :class:`FrameFolderSink` (created when missing)."""
    p = Path(out)
    if p.suffix.lower() in _ROS_STORAGE and not str(out).endswith(os.sep):
        return FrameBagSink(p)
    p.mkdir(parents=True, exist_ok=True)
    return FrameFolderSink(p, stem, fmt)


def read_frames_bag(path, topic: str | None = None) -> list[tuple[int, PointCloud]]:
    """Every PointCloud2 of a bag as ``(stamp_ns, cloud)`` in order (x, y, z float64 of
    the FLOAT32 fields; attributes in their field types)."""
    from rosbags.highlevel import AnyReader

    bag = ros2_bag_dir(path)
    out = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"
                 and (topic is None or c.topic == topic)]
        for conn, stamp, raw in reader.messages(connections=conns):
            out.append((int(stamp), pointcloud2_to_cloud(reader.deserialize(raw, conn.msgtype))))
    return out
