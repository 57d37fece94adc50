"""Scene files: validation errors naming the field, and ray hits on the analytic surfaces."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mems_stereo.errors import FormatError
from mems_stereo.sim import load_scene, scene_from_dict
from mems_stereo.sim.scene import CYLINDER_SEGMENTS, SPHERE_SEGMENTS

SAMPLES = Path(__file__).resolve().parents[1] / "samples"

SPHERE = {"type": "sphere", "center": [0.2, -0.1, 3.0], "radius": 0.5, "reflectivity": 0.4}
CYL = {"type": "cylinder", "center": [-0.3, 0.1, 2.5], "radius": 0.3, "height": 1.0,
       "axis": [0, 1, 0], "reflectivity": 0.6}
BOX = {"type": "box", "center": [0.1, 0.0, 2.0], "size": [0.6, 0.8, 0.4],
       "rotation_deg": [5, 30, -10], "reflectivity": 0.5}
PLANE = {"type": "plane", "center": [0.0, 0.0, 4.0], "normal": [0.1, 0.05, -1.0],
         "size": [6, 6], "reflectivity": 0.7}


def write(tmp_path, d, name="scene.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(d) if not isinstance(d, str) else d)
    return p


def test_sample_scenes_load():
    room = load_scene(SAMPLES / "room_scene.json")
    assert [o.kind for o in room.objects] == ["plane", "box", "cylinder", "box"]
    assert np.all((room.reflectivity > 0) & (room.reflectivity <= 1))
    for d in ("1.5", "2.5", "4.0"):
        sc = load_scene(SAMPLES / f"calib_{d}m_scene.json")
        assert sc.objects[0].kind == "plane"


@pytest.mark.parametrize("obj,field,words", [
    ({**SPHERE, "radius": -1}, "objects[2].radius", "expected a positive number, found -1"),
    ({**SPHERE, "radius": "big"}, "objects[2].radius", "expected a positive number"),
    ({k: v for k, v in SPHERE.items() if k != "reflectivity"}, "objects[2].reflectivity",
     "required field is missing"),
    ({**SPHERE, "reflectivity": 1.5}, "objects[2].reflectivity", "expected a number in (0, 1]"),
    ({**SPHERE, "type": "torus"}, "objects[2].type", "expected one of plane, box"),
    ({**BOX, "size": [1, 2]}, "objects[2].size", "expected a list of 3 numbers"),
    ({**BOX, "size": [1, 0, 2]}, "objects[2].size", "expected 3 positive numbers"),
    ({**PLANE, "normal": [0, 0, 0]}, "objects[2].normal", "expected a non-zero vector"),
    ({**CYL, "height": None}, "objects[2].height", "found null"),
    ({"type": "mesh", "file": "nothere.ply", "reflectivity": 0.5}, "objects[2].file",
     "expected a readable mesh file"),
])
def test_bad_object_names_file_and_field(tmp_path, obj, field, words):
    p = write(tmp_path, {"objects": [PLANE, BOX, obj]})
    with pytest.raises(FormatError) as e:
        load_scene(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: {field}: "), msg
    assert words in msg
    assert e.value.field == field


def test_the_documented_message(tmp_path):
    p = write(tmp_path, {"objects": [PLANE, BOX, {**SPHERE, "radius": -1}]})
    with pytest.raises(FormatError, match=r"scene\.json: objects\[2\]\.radius: expected a "
                                          r"positive number, found -1$"):
        load_scene(p)


@pytest.mark.parametrize("doc,field", [
    ("{not json", None),
    ({"objects": []}, "objects"),
    ({"things": []}, "objects"),
    ({"format": "other", "objects": [SPHERE]}, "format"),
    ([1, 2], "(top level)"),
])
def test_bad_documents(tmp_path, doc, field):
    p = write(tmp_path, doc)
    with pytest.raises(FormatError) as e:
        load_scene(p)
    assert str(e.value).startswith(str(p))
    assert e.value.field == field


def test_missing_file(tmp_path):
    with pytest.raises(FormatError, match="cannot read file"):
        load_scene(tmp_path / "none.json")


# --------------------------------------------------------------------------
# geometry of hits


def _rays_towards(target, spread, u):
    """Unit rays from the origin towards target + spread * u, u in [-1, 1]^3."""
    d = np.asarray(target) + spread * np.asarray(u)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


unit3 = st.lists(st.floats(-1, 1), min_size=3, max_size=3)


@settings(max_examples=40, deadline=None)
@given(st.lists(unit3, min_size=1, max_size=20))
def test_sphere_hits_on_surface(us):
    sc = scene_from_dict({"objects": [SPHERE]})
    d = _rays_towards(SPHERE["center"], 0.45, np.array(us))
    h = sc.cast(np.zeros(3), d)
    c, r = np.array(SPHERE["center"]), SPHERE["radius"]
    # analytic: first root of |t d - c| = r
    b = d @ c
    disc = b ** 2 - (c @ c - r ** 2)
    hit_a = disc > 1e-4  # avoid grazing rays where the facets decide
    assert np.all(h.hit[hit_a])
    t_a = b - np.sqrt(np.where(disc > 0, disc, 0))
    sag = r * (1 - math.cos(math.pi / SPHERE_SEGMENTS[0])) + 2e-5
    err = np.abs(np.linalg.norm(h.point[hit_a] - c, axis=1) - r)
    assert np.all(err < sag)
    deep = disc > 0.05 * r ** 2  # away from the silhouette the range is accurate too
    assert np.all(np.abs(h.t[deep] - t_a[deep]) < 20 * sag)
    # normals face the ray
    assert np.all(np.sum(h.normal[h.hit] * d[h.hit], axis=1) < 0)


@settings(max_examples=40, deadline=None)
@given(st.lists(unit3, min_size=1, max_size=20))
def test_cylinder_hits_on_surface(us):
    sc = scene_from_dict({"objects": [CYL]})
    d = _rays_towards(CYL["center"], 0.4, np.array(us))
    h = sc.cast(np.zeros(3), d)
    c = np.array(CYL["center"])
    p = h.point[h.hit] - c
    radial = np.hypot(p[:, 0], p[:, 2])
    sag = CYL["radius"] * (1 - math.cos(math.pi / CYLINDER_SEGMENTS)) + 2e-5
    on_side = np.abs(radial - CYL["radius"]) < sag
    on_cap = (np.abs(np.abs(p[:, 1]) - 0.5 * CYL["height"]) < 1e-9) & (radial <= 0.3 + 1e-5)
    assert np.all(on_side | on_cap)
    assert np.all(np.abs(p[:, 1]) <= 0.5 * CYL["height"] + 2e-5)


@settings(max_examples=40, deadline=None)
@given(st.lists(unit3, min_size=1, max_size=20))
def test_box_and_plane_hits_on_surface(us):
    sc = scene_from_dict({"objects": [BOX, PLANE]})
    d = _rays_towards(BOX["center"], 1.2, np.array(us))
    h = sc.cast(np.zeros(3), d)
    obj = sc.objects
    on_box = h.object_index == 0
    R = obj[0].params["rotation"]
    local = (h.point[on_box] - BOX["center"]) @ R  # box frame
    half = 0.5 * np.array(BOX["size"])
    # hits are float64 ray-plane intersections of the triangle Embree picked (float32)
    assert np.all(np.abs(local) <= half + 2e-5)
    assert np.all(np.min(np.abs(np.abs(local) - half), axis=1) < 1e-9)
    on_plane = h.object_index == 1
    n = obj[1].params["normal"]
    assert np.all(np.abs((h.point[on_plane] - PLANE["center"]) @ n) < 1e-9)
    # the box is in front of the plane: a ray that meets both stops at the box
    assert np.all(h.t[on_box] < 4.0)


def test_mesh_file(tmp_path):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)  # [0, 1]^3
    o3d.io.write_triangle_mesh(str(tmp_path / "cube.ply"), mesh)
    p = write(tmp_path, {"objects": [{"type": "mesh", "file": "cube.ply", "scale": 0.5,
                                      "translation": [-0.25, -0.25, 3.0],
                                      "reflectivity": 0.3}]})
    sc = load_scene(p)
    h = sc.cast(np.zeros(3), np.array([[0.0, 0.0, 1.0]]))
    assert h.object_index[0] == 0
    assert h.t[0] == pytest.approx(3.0, abs=1e-5)
    np.testing.assert_allclose(h.normal[0], [0, 0, -1], atol=1e-6)
