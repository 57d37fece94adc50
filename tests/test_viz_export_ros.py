"""Clouds out: ROS 2 bags (MCAP, SQLite) read back by rosbags, stamped with the cloud's
time (a recording's shot clock, or --stamp), and LAZ out of the box."""

from __future__ import annotations

import calendar
import shutil

import h5py
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
from mems_stereo.viz.export_ros2 import (
    cloud_stamp_ns,
    parse_stamp,
    read_ros2_stamp,
    recording_stamp_ns,
)

from mems_stereo import data
from mems_stereo.cli import main as cli_main
from mems_stereo.errors import FormatError, OptionError
from mems_stereo.pipeline.cloud import PointCloud

#: 2026-11-27T08:00:00.25Z in ns, by the calendar module (independent of parse_stamp)
T_ISO = "2026-11-27T08:00:00.25Z"
T_NS = calendar.timegm((2026, 11, 27, 8, 0, 0)) * 10**9 + 250_000_000


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
    bag = write_cloud(tmp_path / f"room.{ext}", ref, stamp_ns=T_NS)
    assert bag == tmp_path / "room" and (bag / f"room.{ext}").is_file()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(bag) as r:
        assert r.message_count == 1
        (conn,) = r.connections
        assert (conn.topic, conn.msgtype) == (ROS_TOPIC, "sensor_msgs/msg/PointCloud2")
        (_, stamp, raw), = list(r.messages())
    m = ts.deserialize_cdr(raw, conn.msgtype)
    assert m.header.frame_id == ROS_FRAME_ID
    # the cloud's time, in the message and as the bag's log time (never the time of export)
    assert stamp == T_NS and (m.header.stamp.sec, m.header.stamp.nanosec) == (
        T_NS // 10**9, 250_000_000)
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
    assert read_ros2_stamp(tmp_path / "a.mcap") == 1_700_000_000_123
    # export infers the format from the suffix, both ways; an existing bag is replaced
    write_cloud(tmp_path / "c.ply", ref)
    ply, db3 = str(tmp_path / "c.ply"), str(tmp_path / "c.db3")
    # a PLY carries no acquisition time: a bag from it needs --stamp, refused before any work
    assert cli_main(["export", ply, "-o", db3]) == 2
    err = capsys.readouterr().err
    assert "--stamp" in err and "c.ply" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()
    assert cli_main(["export", ply, "-o", db3, "--stamp", "1764230400.5"]) == 0
    assert read_ros2_stamp(db3) == 1_764_230_400_500_000_000  # exact, no float rounding
    # a bag keeps its own stamp through export; a stamp for a PLY output is refused
    assert cli_main(["export", db3, "-o", str(tmp_path / "e.mcap")]) == 0
    assert read_ros2_stamp(tmp_path / "e.mcap") == 1_764_230_400_500_000_000
    assert cli_main(["export", db3, "-o", str(tmp_path / "d.ply"), "--stamp", "now"]) == 2
    assert cli_main(["export", db3, "-o", str(tmp_path / "d.ply")]) == 0
    assert len(read_cloud(tmp_path / "d.ply")) == 50
    assert not list(tmp_path.glob(".*part*"))


def test_stamp_parsing_against_the_calendar():
    assert parse_stamp(T_ISO) == T_NS
    assert parse_stamp("2026-11-27T09:00:00.25+01:00") == T_NS
    assert parse_stamp(str(T_NS // 10**9) + ".25") == T_NS
    assert parse_stamp("0") == 0
    import time

    assert abs(parse_stamp("now") - time.time_ns()) < 5 * 10**9
    for bad in ("2026-11-27T08:00:00", "yesterday", "-1", "nan", "1e30"):
        with pytest.raises(OptionError, match="--stamp"):
            parse_stamp(bad)
    with pytest.raises(FormatError, match="stamp"):  # the API needs the cloud's time too
        write_cloud("x.mcap", _cloud(5))


def test_process_stamps_the_bag_with_the_recording_shot_clock(tmp_path):
    """A copy of room.h5 whose clock starts 1000.25 s later: the bag's stamp moves with
    it (shot times and zero crossings shifted alike, the scan angles unchanged)."""
    rec = tmp_path / "late.h5"
    shutil.copy(data.path("room.h5"), rec)
    with h5py.File(rec, "r+") as f:
        t0 = float(f["shots/time"][0])
        f["shots/time"][...] = f["shots/time"][...] + 1000.25
        f["scanner/zero_crossings"][...] = f["scanner/zero_crossings"][...] + 1000.25
    want = int(round((t0 + 1000.25) * 1e9))
    assert recording_stamp_ns(rec) == want
    assert cli_main(["process", "-q", str(rec), "-o", str(tmp_path / "late.mcap")]) == 0
    assert read_ros2_stamp(tmp_path / "late.mcap") == want
    assert len(read_cloud(tmp_path / "late.mcap")) > 0
    # --stamp overrides the shot clock; a cloud that is no bag is not stamped
    assert cloud_stamp_ns(tmp_path / "o.db3", T_ISO, rec) == T_NS
    assert cloud_stamp_ns(tmp_path / "o.db3", None, rec) == want
    assert cloud_stamp_ns(tmp_path / "o.ply", None, rec) is None
    assert cli_main(["process", "-q", str(rec), "-o", str(tmp_path / "o.ply"),
                     "--stamp", T_ISO]) == 2  # nothing to stamp: refused before any work
    assert not (tmp_path / "o.ply").exists()


def test_ros2_bag_refuses_to_replace_a_non_bag(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "keep.txt").write_text("x")
    with pytest.raises(FormatError, match="not a ROS 2 bag"):
        write_cloud(tmp_path / "data.mcap", _cloud(5), stamp_ns=0)
    assert (tmp_path / "data" / "keep.txt").exists()
    assert ros2_bag_dir("x/y.db3").name == "y"
    big = _cloud(5)
    big.attributes["huge"] = np.array([2**40] * 5, dtype=np.int64)
    with pytest.raises(FormatError, match="huge"):
        write_cloud(tmp_path / "h.mcap", big, stamp_ns=0)


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
