"""Clouds out: ROS 2 bags (MCAP, SQLite) read back by rosbags, and LAZ out of the box."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from mems_stereo.viz.export import (
    LAS_SCALE,
    ROS_FRAME_ID,
    ROS_TOPIC,
    read_cloud,
    ros2_bag_dir,
    write_cloud,
    write_ros2_bag,
)

from mems_stereo.cli import main as cli_main
from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud


def _cloud(n=300, seed=4):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-2, 2, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.5, 8, n)]
    return PointCloud(pts, {
        "counts": rng.integers(1, 5000, n).astype(np.int32),
        "pixel": rng.integers(0, 192, n).astype(np.int32),
        "range": np.linalg.norm(pts, axis=1),
        "sigma_r": rng.uniform(1e-4, 0.05, n),
        "sigma_phi": rng.uniform(1e-5, 1e-3, n),
        "label": rng.integers(0, 3, n).astype(np.uint8),
        "f32": rng.normal(size=n).astype(np.float32),
        "u16": rng.integers(0, 65535, n).astype(np.uint16),
        "i64": rng.integers(-5, 5, n).astype(np.int64),
        "flag": rng.random(n) < 0.5,
    })


@pytest.mark.parametrize("ext", ["mcap", "db3"])
def test_ros2_bag_read_back_by_rosbags(tmp_path, ext):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    ref = _cloud()
    bag = write_cloud(tmp_path / f"room.{ext}", ref)
    assert bag == tmp_path / "room" and (bag / f"room.{ext}").is_file()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(bag) as r:
        assert r.message_count == 1
        (conn,) = r.connections
        assert (conn.topic, conn.msgtype) == (ROS_TOPIC, "sensor_msgs/msg/PointCloud2")
        (_, stamp, raw), = list(r.messages())
    m = ts.deserialize_cdr(raw, conn.msgtype)
    assert m.header.frame_id == ROS_FRAME_ID
    assert m.width * m.height == len(ref) and m.row_step == m.point_step * m.width
    names = [f.name for f in m.fields]
    assert names == ["x", "y", "z", *ref.attributes]
    # parse the bytes independently of viz.export: offsets and datatypes from the message
    pf = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
    dt = np.dtype({"names": names, "formats": [pf[f.datatype] for f in m.fields],
                   "offsets": [f.offset for f in m.fields], "itemsize": m.point_step})
    a = np.frombuffer(bytes(m.data), dtype=dt)
    np.testing.assert_array_equal(a["x"], ref.points[:, 0].astype(np.float32))
    np.testing.assert_array_equal(a["z"], ref.points[:, 2].astype(np.float32))
    for k, v in ref.attributes.items():
        np.testing.assert_array_equal(a[k], v, err_msg=k)
    assert {f.name: f.datatype for f in m.fields}["i64"] == 5  # INT32: the values fit
    assert {f.name: f.datatype for f in m.fields}["flag"] == 2  # UINT8


def test_ros2_bag_round_trip_through_read_cloud_and_cli(tmp_path, capsys):
    ref = _cloud(50)
    write_ros2_bag(tmp_path / "a.mcap", ref, frame_id="lidar", stamp_ns=1_700_000_000_123)
    back = read_cloud(tmp_path / "a.mcap")
    assert len(back) == 50
    np.testing.assert_allclose(back.points, ref.points, rtol=1e-7)
    np.testing.assert_array_equal(back["range"], ref["range"])
    assert back["range"].dtype == np.float64 and back["u16"].dtype == np.uint16
    # export infers the format from the suffix, both ways; an existing bag is replaced
    write_cloud(tmp_path / "c.ply", ref)
    assert cli_main(["export", str(tmp_path / "c.ply"), "-o", str(tmp_path / "c.db3")]) == 0
    assert cli_main(["export", str(tmp_path / "c.ply"), "-o", str(tmp_path / "c.db3")]) == 0
    assert cli_main(["export", str(tmp_path / "c.db3"), "-o", str(tmp_path / "d.ply")]) == 0
    assert len(read_cloud(tmp_path / "d.ply")) == 50
    assert not list(tmp_path.glob(".*part*"))


def test_ros2_bag_refuses_to_replace_a_non_bag(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "keep.txt").write_text("x")
    with pytest.raises(FormatError, match="not a ROS 2 bag"):
        write_cloud(tmp_path / "data.mcap", _cloud(5))
    assert (tmp_path / "data" / "keep.txt").exists()
    assert ros2_bag_dir("x/y.db3").name == "y"
    big = _cloud(5)
    big.attributes["huge"] = np.array([2**40] * 5, dtype=np.int64)
    with pytest.raises(FormatError, match="huge"):
        write_cloud(tmp_path / "h.mcap", big)


def test_laz_round_trip_out_of_the_box(tmp_path):
    assert laspy.LazBackend.detect_available()
    ref = _cloud(400)
    del ref.attributes["flag"]
    p = write_cloud(tmp_path / "c.laz", ref)
    with laspy.open(str(p)) as f:
        assert f.header.are_points_compressed and f.header.point_count == 400
    back = read_cloud(p)
    assert np.abs(back.points - ref.points).max() <= LAS_SCALE / 2 + 1e-12
    for k, v in ref.attributes.items():
        np.testing.assert_array_equal(back[k], v, err_msg=k)
    assert p.stat().st_size < write_cloud(tmp_path / "c.las", ref).stat().st_size
