"""Point cloud files: PLY/PCD exact round trips, LAS within its scale, errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mems_stereo.viz.export import LAS_SCALE, read_cloud, write_cloud

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud


def make_cloud(rng: np.random.Generator, n: int = 50) -> PointCloud:
    pts = np.c_[rng.uniform(-2, 2, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.5, 8, n)]
    return PointCloud(pts, {
        "counts": rng.integers(1, 5000, n).astype(np.int32),
        "pixel": rng.integers(0, 192, n).astype(np.int32),
        "range": np.linalg.norm(pts, axis=1),
        "sigma_r": rng.uniform(1e-4, 0.05, n),
        "sigma_phi": rng.uniform(1e-5, 1e-3, n),
        "row": np.zeros(n, np.int32),
        "label": rng.integers(0, 3, n).astype(np.uint8),
        "sigma_x": rng.uniform(0, 0.01, n),
        "code": rng.uniform(1, 4096, n),
        "f32": rng.normal(size=n).astype(np.float32),
        "u16": rng.integers(0, 65535, n).astype(np.uint16),
    })


def assert_same_attributes(got: PointCloud, ref: PointCloud):
    assert set(got.attributes) == set(ref.attributes)
    for k, v in ref.attributes.items():
        assert got[k].dtype == v.dtype, k
        np.testing.assert_array_equal(got[k], v, err_msg=k)


@pytest.mark.parametrize("ext", ["ply", "pcd"])
def test_open3d_round_trip_is_exact(tmp_path, ext):
    ref = make_cloud(np.random.default_rng(1))
    read = read_cloud(write_cloud(tmp_path / f"c.{ext}", ref))
    assert read.points.dtype == np.float64
    np.testing.assert_array_equal(read.points, ref.points)
    assert_same_attributes(read, ref)


def test_ply_is_binary_with_double_xyz(tmp_path):
    p = write_cloud(tmp_path / "c.ply", make_cloud(np.random.default_rng(2), 3))
    head = p.read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian" in head
    for axis in "xyz":
        assert f"property double {axis}\n" in head
    for name in ("counts", "pixel", "range", "sigma_r", "sigma_phi"):
        assert f" {name}\n" in head


def test_las_round_trip_within_scale(tmp_path):
    ref = make_cloud(np.random.default_rng(3), 500)
    read = read_cloud(write_cloud(tmp_path / "c.las", ref))
    err = np.abs(read.points - ref.points)
    assert err.max() <= LAS_SCALE / 2 * (1 + 1e-9)
    assert err.max() > 0  # the coordinates really are quantised
    assert_same_attributes(read, ref)


def test_las_intensity_carries_counts(tmp_path):
    import laspy

    ref = make_cloud(np.random.default_rng(4), 20)
    las = laspy.read(write_cloud(tmp_path / "c.las", ref))
    np.testing.assert_array_equal(np.asarray(las.intensity), ref["counts"])


@settings(max_examples=15, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-1e3, 1e3, allow_nan=False)] * 3), min_size=1,
                max_size=20))
def test_las_precision_property(tmp_path_factory, xyz):
    pts = np.array(xyz, dtype=np.float64)
    path = tmp_path_factory.mktemp("las") / "p.las"
    read = read_cloud(write_cloud(path, PointCloud(pts)))
    assert np.abs(read.points - pts).max() <= LAS_SCALE / 2 * (1 + 1e-6)


@pytest.mark.parametrize("ext", ["ply", "pcd", "las"])
def test_empty_cloud_round_trip(tmp_path, ext):
    ref = make_cloud(np.random.default_rng(5), 4).select(np.zeros(4, bool))
    read = read_cloud(write_cloud(tmp_path / f"e.{ext}", ref))
    assert len(read) == 0
    assert_same_attributes(read, ref)


def test_nan_points_kept_in_ply_refused_in_las(tmp_path):
    ref = make_cloud(np.random.default_rng(6), 5)
    ref.points[2] = np.nan
    read = read_cloud(write_cloud(tmp_path / "n.ply", ref))
    np.testing.assert_array_equal(read.points, ref.points)
    with pytest.raises(FormatError, match="non-finite"):
        write_cloud(tmp_path / "n.las", ref)
    assert not (tmp_path / "n.las").exists()


def test_dtype_conversions(tmp_path):
    n = 6
    c = PointCloud(np.zeros((n, 3)) + 1.0, {"i64": np.arange(n, dtype=np.int64),
                                            "flag": np.arange(n) % 2 == 0})
    ply = read_cloud(write_cloud(tmp_path / "d.ply", c))
    assert ply["i64"].dtype == np.int32 and ply["flag"].dtype == np.uint8
    np.testing.assert_array_equal(ply["i64"], c["i64"])
    np.testing.assert_array_equal(ply["flag"], c["flag"].astype(np.uint8))
    pcd = read_cloud(write_cloud(tmp_path / "d.pcd", c))
    assert pcd["i64"].dtype == np.int64  # PCD keeps int64
    big = PointCloud(np.ones((2, 3)), {"big": np.array([0, 2**40], np.int64)})
    with pytest.raises(FormatError, match="big"):
        write_cloud(tmp_path / "big.ply", big)


@pytest.mark.parametrize("name", ["colors", "x"])
def test_reserved_names_refused(tmp_path, name):
    c = PointCloud(np.ones((2, 3)), {name: np.ones(2)})
    with pytest.raises(FormatError, match=name):
        write_cloud(tmp_path / "r.ply", c)


def test_las_name_clash_refused(tmp_path):
    c = PointCloud(np.ones((2, 3)), {"intensity": np.ones(2)})
    with pytest.raises(FormatError, match="intensity"):
        write_cloud(tmp_path / "r.las", c)


def test_bad_paths(tmp_path):
    c = make_cloud(np.random.default_rng(7), 3)
    with pytest.raises(FormatError, match="extension"):
        write_cloud(tmp_path / "c.xyz", c)
    with pytest.raises(FormatError, match="extension"):
        read_cloud(tmp_path / "c.txt")
    with pytest.raises(FileNotFoundError):
        read_cloud(tmp_path / "missing.ply")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(FormatError, match="directory"):
        write_cloud(tmp_path / "dir.ply", c)
    for ext in ("ply", "pcd", "las"):
        bad = tmp_path / f"garbage.{ext}"
        bad.write_bytes(b"not a point cloud\n")
        with pytest.raises(FormatError, match="garbage"):
            read_cloud(bad)
    with pytest.raises(FormatError, match="PointCloud"):
        write_cloud(tmp_path / "c.ply", np.zeros((3, 3)))


def test_failed_write_leaves_target_untouched(tmp_path, monkeypatch):
    import mems_stereo.viz.export as ex

    def boom(tmp, points, attrs):
        tmp.write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(ex, "_write_ply", boom)
    monkeypatch.setattr(ex, "_write_o3d", boom)
    for name in ("keep.ply", "keep.pcd"):
        target = tmp_path / name
        target.write_bytes(b"old")
        with pytest.raises(KeyboardInterrupt):
            write_cloud(target, make_cloud(np.random.default_rng(8), 3))
        assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.pcd", "keep.ply"]


def test_laz_without_backend_says_what_to_install(tmp_path):
    import laspy

    if laspy.LazBackend.detect_available():
        pytest.skip("a LAZ backend is installed; .laz works")
    with pytest.raises(FormatError, match="lazrs"):
        write_cloud(tmp_path / "c.laz", make_cloud(np.random.default_rng(9), 3))


def test_ply_written_without_open3d_has_open3d_fields(tmp_path):
    """The NumPy PLY writer gives the properties and types Open3D writes, and Open3D
    reads it back exactly; writing it does not import Open3D."""
    import subprocess
    import sys

    import open3d as o3d

    ref = make_cloud(np.random.default_rng(10), 40)
    ours = write_cloud(tmp_path / "ours.ply", ref)
    theirs = tmp_path / "o3d.ply"
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(ref.points))
    for k, v in ref.attributes.items():
        pc.point[k] = o3d.core.Tensor(np.ascontiguousarray(v.reshape(-1, 1)))
    assert o3d.t.io.write_point_cloud(str(theirs), pc, write_ascii=False, compressed=False)

    def props(p):
        head = p.read_bytes().split(b"end_header")[0].decode().splitlines()
        return sorted(ln for ln in head if ln.startswith(("property", "element", "format")))

    assert props(ours) == props(theirs)
    back = o3d.t.io.read_point_cloud(str(ours))
    np.testing.assert_array_equal(back.point.positions.numpy(), ref.points)
    for k, v in ref.attributes.items():
        got = back.point[k].numpy()[:, 0]
        assert got.dtype == v.dtype, k
        np.testing.assert_array_equal(got, v, err_msg=k)
    code = ("import sys; import numpy as np; from mems_stereo.viz.export import write_cloud; "
            "from mems_stereo.pipeline.cloud import PointCloud; "
            f"write_cloud({str(tmp_path / 'sub.ply')!r}, PointCloud(np.ones((3, 3)), "
            "{'counts': np.ones(3, np.int32)})); print('open3d' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
