"""Scenes for the simulator: primitives and meshes with a reflectivity, ray casting.

A scene is a JSON file (``docs/simulator.md``)::

    {"format": "mems-stereo/scene", "version": 1, "name": "room",
     "objects": [
       {"type": "plane", "center": [0, 0, 5], "normal": [0, 0, -1], "size": [8, 3],
        "reflectivity": 0.6},
       {"type": "box", "center": [-0.5, 0.2, 1.5], "size": [0.4, 1.0, 0.4],
        "rotation_deg": [0, 20, 0], "reflectivity": 0.5},
       {"type": "sphere", "center": [0, 0, 2], "radius": 0.3, "reflectivity": 0.4},
       {"type": "cylinder", "center": [0.3, 0, 2.5], "radius": 0.15, "height": 1.2,
        "axis": [0, 1, 0], "reflectivity": 0.7},
       {"type": "mesh", "file": "bunny.ply", "scale": 1.0, "translation": [0, 0, 3],
        "rotation_deg": [0, 0, 0], "reflectivity": 0.5}]}

All coordinates are metres in the world frame (the receiver camera frame,
OpenCV convention: x right, y down, z forward).  Every object becomes a
triangle mesh; rays are cast with ``open3d.t.geometry.RaycastingScene``
(imported lazily, so the package imports without Open3D).  Smooth primitives
are tessellated finely (sagitta below 0.1 mm for objects under 1 m).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.util.jsonfile import FieldChecker, check_schema, read_json_file
from mems_stereo.util.paths import require_input_file
from mems_stereo.util.schemas import SCENE_FIELDS

SCENE_FORMAT = "mems-stereo/scene"
SCENE_VERSION = 1
OBJECT_TYPES = ("plane", "box", "sphere", "cylinder", "mesh")
CYLINDER_SEGMENTS = 256
SPHERE_SEGMENTS = (128, 256)  # (latitude, longitude)


@dataclass
class SceneObject:
    """One object of a scene, as triangles.

    Attributes
    ----------
    kind : one of ``OBJECT_TYPES``.
    name : label for messages and truth.
    reflectivity : float in (0, 1], Lambertian albedo at the laser wavelength.
    vertices : (V, 3) float64, metres, world frame.
    triangles : (T, 3) int64 vertex indices.
    params : the validated JSON parameters (centre, radius, ...), for tests.
    """

    kind: str
    name: str
    reflectivity: float
    vertices: np.ndarray
    triangles: np.ndarray
    params: dict = field(default_factory=dict)


@dataclass
class RayHits:
    """Result of :meth:`Scene.cast`, one entry per ray.

    t : (N,) float64, metres along the unit ray (inf: no hit).
    point : (N, 3) float64, world frame (NaN: no hit).
    normal : (N, 3) float64 unit surface normal facing the ray's origin (NaN: no hit).
    object_index : (N,) int64, index into ``Scene.objects`` (-1: no hit).
    """

    t: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    object_index: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.object_index >= 0


class Scene:
    """Objects with reflectivities, and a lazily built Open3D ray-casting scene."""

    def __init__(self, objects: list[SceneObject], name: str = "", source: str = "<memory>"):
        self.objects = list(objects)
        self.name = name
        self.source = source
        self._rc = None
        self._gid_to_obj: np.ndarray | None = None

    @property
    def reflectivity(self) -> np.ndarray:
        """(n_objects,) float64 reflectivities."""
        return np.array([o.reflectivity for o in self.objects], dtype=np.float64)

    def _raycaster(self):
        if self._rc is None:
            import open3d as o3d

            rc = o3d.t.geometry.RaycastingScene()
            ids = []
            for i, o in enumerate(self.objects):
                gid = rc.add_triangles(
                    o3d.core.Tensor(np.ascontiguousarray(o.vertices, dtype=np.float32)),
                    o3d.core.Tensor(np.ascontiguousarray(o.triangles, dtype=np.uint32)))
                ids.append((int(gid), i))
            lut = np.full(max([g for g, _ in ids], default=0) + 1, -1, dtype=np.int64)
            for g, i in ids:
                lut[g] = i
            self._gid_to_obj = lut
            self._rc = rc
        return self._rc

    def cast(self, origins, directions) -> RayHits:
        """Cast rays; first hit of each.

        origins : (N, 3) or (3,) metres; directions : (N, 3) unit vectors.
        """
        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), d.shape)
        n = d.shape[0]
        if n == 0 or not self.objects:
            return RayHits(np.full(n, np.inf), np.full((n, 3), np.nan),
                           np.full((n, 3), np.nan), np.full(n, -1, dtype=np.int64))
        import open3d as o3d

        rc = self._raycaster()
        rays = np.concatenate([o, d], axis=1).astype(np.float32)
        ans = rc.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        obj = np.full(n, -1, dtype=np.int64)
        obj[hit] = self._gid_to_obj[gid[hit]]
        hit &= obj >= 0
        t[~hit] = np.inf
        pts = np.full((n, 3), np.nan)
        nrm = np.full((n, 3), np.nan)
        if np.any(hit):
            # Embree casts in float32 (and its SIMD path differs between CPUs): it only
            # picks the triangle; the hit itself is the float64 ray-plane intersection
            nn = np.empty((n, 3))
            v0 = np.empty((n, 3))
            for i in np.unique(obj[hit]):
                sel = hit & (obj == i)
                ob = self.objects[i]
                tri = np.asarray(ob.vertices, dtype=np.float64)[ob.triangles[prim[sel]]]
                v0[sel] = tri[:, 0]
                nn[sel] = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            nh, dh = nn[hit], d[hit]
            nh /= np.linalg.norm(nh, axis=1, keepdims=True)
            t[hit] = np.sum((v0[hit] - o[hit]) * nh, axis=1) / np.sum(dh * nh, axis=1)
            flip = np.sum(nh * dh, axis=1) > 0  # face the incoming ray
            nh[flip] *= -1.0
            nrm[hit] = nh
            pts[hit] = o[hit] + t[hit, None] * dh
        return RayHits(t, pts, nrm, obj)

    def __repr__(self) -> str:
        kinds = ", ".join(o.kind for o in self.objects)
        return f"Scene({self.name!r}, {len(self.objects)} objects: {kinds})"


# --------------------------------------------------------------------------
# geometry builders (NumPy, no Open3D needed)


def rotation_from_euler_deg(angles) -> np.ndarray:
    """R = Rz · Ry · Rx for ``rotation_deg = [rx, ry, rz]`` (extrinsic x, then y, then z)."""
    rx, ry, rz = np.radians(np.asarray(angles, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = (math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry),
                              math.cos(rz), math.sin(rz))
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is the unit ``axis``."""
    a = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, a)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    return np.stack([u, v, a], axis=1)


def plane_mesh(center, normal, size, up=(0.0, -1.0, 0.0)):
    """A rectangle ``size = [width, height]`` centred at ``center`` facing ``normal``.

    Width runs along ``up × normal``, height along ``normal × width``.
    Returns vertices (4, 3) and triangles (2, 3).
    """
    c = np.asarray(center, float)
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    up = np.asarray(up, float)
    a = np.cross(up, n)
    if np.linalg.norm(a) < 1e-9:
        a = np.cross([1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0], n)
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    w, h = 0.5 * size[0], 0.5 * size[1]
    v = np.array([c - w * a - h * b, c + w * a - h * b, c + w * a + h * b, c - w * a + h * b])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def box_mesh(center, size, R=None):
    """Axis-aligned box of ``size = [sx, sy, sz]`` rotated by R about its centre.

    Returns vertices (8, 3) and triangles (12, 3), outward winding.
    """
    s = 0.5 * np.asarray(size, float)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * s
    R = np.eye(3) if R is None else R
    v = corners @ R.T + np.asarray(center, float)
    # corner index = 4*ix + 2*iy + iz
    tris = np.array([
        [0, 1, 3], [0, 3, 2],  # x = -
        [4, 6, 7], [4, 7, 5],  # x = +
        [0, 4, 5], [0, 5, 1],  # y = -
        [2, 3, 7], [2, 7, 6],  # y = +
        [0, 2, 6], [0, 6, 4],  # z = -
        [1, 5, 7], [1, 7, 3],  # z = +
    ])
    return v, tris


def sphere_mesh(center, radius, n_lat=SPHERE_SEGMENTS[0], n_lon=SPHERE_SEGMENTS[1]):
    """UV sphere: vertices ((n_lat-1)*n_lon + 2, 3), triangles (2*n_lon*(n_lat-1), 3)."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(LA) * np.cos(LO), np.cos(LA), np.sin(LA) * np.sin(LO)], -1)
    v = np.concatenate([[[0, 1, 0]], ring.reshape(-1, 3), [[0, -1, 0]]]) * radius
    v = v + np.asarray(center, float)
    tris = []
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    tris.append(np.stack([np.zeros(n_lon, int), 1 + jn, 1 + j], 1))
    for i in range(n_lat - 2):
        a, b = 1 + i * n_lon, 1 + (i + 1) * n_lon
        tris.append(np.stack([a + j, a + jn, b + jn], 1))
        tris.append(np.stack([a + j, b + jn, b + j], 1))
    last = v.shape[0] - 1
    a = 1 + (n_lat - 2) * n_lon
    tris.append(np.stack([np.full(n_lon, last), a + j, a + jn], 1))
    return v, np.concatenate(tris)


def cylinder_mesh(center, radius, height, axis=(0.0, 1.0, 0.0), n_seg=CYLINDER_SEGMENTS):
    """Closed cylinder (with caps) about ``axis`` through ``center``."""
    R = _frame_from_axis(np.asarray(axis, float))
    ang = np.linspace(0, 2 * np.pi, n_seg, endpoint=False)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(n_seg)], 1)
    bottom = ring - [0, 0, 0.5 * height]
    top = ring + [0, 0, 0.5 * height]
    v = np.concatenate([bottom, top, [[0, 0, -0.5 * height], [0, 0, 0.5 * height]]])
    j = np.arange(n_seg)
    jn = (j + 1) % n_seg
    side = np.concatenate([np.stack([j, jn, n_seg + jn], 1),
                           np.stack([j, n_seg + jn, n_seg + j], 1)])
    cb, ct = 2 * n_seg, 2 * n_seg + 1
    caps = np.concatenate([np.stack([np.full(n_seg, cb), jn, j], 1),
                           np.stack([np.full(n_seg, ct), n_seg + j, n_seg + jn], 1)])
    v = v @ R.T + np.asarray(center, float)
    return v, np.concatenate([side, caps])


# --------------------------------------------------------------------------
# JSON loading and validation


class _Checker(FieldChecker):
    """Scene-specific checks on top of the shared field checker."""

    def vec(self, v: Any, fld: str, n: int, positive: bool = False,
            nonzero: bool = False) -> np.ndarray:
        ok = isinstance(v, (list, tuple)) and len(v) == n and all(
            not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)
            for x in v)
        if not ok:
            raise self.fail(fld, f"expected a list of {n} numbers, found {json.dumps(v)}")
        a = np.asarray(v, dtype=np.float64)
        if positive and np.any(a <= 0):
            raise self.fail(fld, f"expected {n} positive numbers, found {json.dumps(v)}")
        if nonzero and np.linalg.norm(a) < 1e-12:
            raise self.fail(fld, f"expected a non-zero vector, found {json.dumps(v)}")
        return a


def _object_from_dict(o: Any, i: int, ck: _Checker, base_dir: Path) -> SceneObject:
    pre = f"objects[{i}]"
    if not isinstance(o, dict):
        raise ck.fail(pre, f"expected an object, found {json.dumps(o)}")
    kind = ck.req(o, "type", pre)
    if kind not in OBJECT_TYPES:
        raise ck.fail(f"{pre}.type", f"expected one of {', '.join(OBJECT_TYPES)}, found "
                                     f"{json.dumps(kind)}")
    refl = ck.number(ck.req(o, "reflectivity", pre), f"{pre}.reflectivity")
    if not 0.0 < refl <= 1.0:
        raise ck.fail(f"{pre}.reflectivity", f"expected a number in (0, 1], found {refl:g}")
    name = o.get("name", f"{kind}{i}")
    if not isinstance(name, str):
        raise ck.fail(f"{pre}.name", f"expected a string, found {json.dumps(name)}")
    p: dict[str, Any] = {}
    if kind == "plane":
        p["center"] = ck.vec(ck.req(o, "center", pre), f"{pre}.center", 3)
        p["normal"] = ck.vec(ck.req(o, "normal", pre), f"{pre}.normal", 3, nonzero=True)
        p["size"] = ck.vec(ck.req(o, "size", pre), f"{pre}.size", 2, positive=True)
        p["up"] = ck.vec(o.get("up", [0.0, -1.0, 0.0]), f"{pre}.up", 3, nonzero=True)
        v, t = plane_mesh(p["center"], p["normal"], p["size"], p["up"])
        p["normal"] = p["normal"] / np.linalg.norm(p["normal"])
    elif kind == "box":
        p["center"] = ck.vec(ck.req(o, "center", pre), f"{pre}.center", 3)
        p["size"] = ck.vec(ck.req(o, "size", pre), f"{pre}.size", 3, positive=True)
        p["rotation"] = rotation_from_euler_deg(
            ck.vec(o.get("rotation_deg", [0, 0, 0]), f"{pre}.rotation_deg", 3))
        v, t = box_mesh(p["center"], p["size"], p["rotation"])
    elif kind == "sphere":
        p["center"] = ck.vec(ck.req(o, "center", pre), f"{pre}.center", 3)
        p["radius"] = ck.number(ck.req(o, "radius", pre), f"{pre}.radius", positive=True)
        v, t = sphere_mesh(p["center"], p["radius"])
    elif kind == "cylinder":
        p["center"] = ck.vec(ck.req(o, "center", pre), f"{pre}.center", 3)
        p["radius"] = ck.number(ck.req(o, "radius", pre), f"{pre}.radius", positive=True)
        p["height"] = ck.number(ck.req(o, "height", pre), f"{pre}.height", positive=True)
        p["axis"] = ck.vec(o.get("axis", [0.0, 1.0, 0.0]), f"{pre}.axis", 3, nonzero=True)
        p["axis"] = p["axis"] / np.linalg.norm(p["axis"])
        v, t = cylinder_mesh(p["center"], p["radius"], p["height"], p["axis"])
    else:  # mesh
        v, t, mesh_params = _mesh_from_file(o, pre, ck, base_dir)
        p.update(mesh_params)
    for key in ("velocity", "angular_rate"):  # motion (mems_stereo.sim.motion)
        if key in o:
            p[key] = ck.vec(o[key], f"{pre}.{key}", 3)
    return SceneObject(kind, name, refl, np.asarray(v, float), np.asarray(t, np.int64), p)


def _mesh_from_file(o: dict, pre: str, ck: _Checker,
                    base_dir: Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """A ``mesh`` object's vertices (V, 3) m, triangles (T, 3) and parameters."""
    fname = ck.req(o, "file", pre)
    if not isinstance(fname, str) or not fname:
        raise ck.fail(f"{pre}.file", f"expected a file name, found {json.dumps(fname)}")
    path = _confined_mesh_path(fname, base_dir, ck, f"{pre}.file")
    scale = ck.number(o.get("scale", 1.0), f"{pre}.scale", positive=True)
    trans = ck.vec(o.get("translation", [0, 0, 0]), f"{pre}.translation", 3)
    R = rotation_from_euler_deg(ck.vec(o.get("rotation_deg", [0, 0, 0]),
                                       f"{pre}.rotation_deg", 3))
    try:
        require_input_file(path)
    except (FileNotFoundError, FormatError):
        raise ck.fail(f"{pre}.file", f"expected a readable mesh file, found no regular "
                                     f"file {fname}") from None
    import open3d as o3d

    try:
        mesh = o3d.io.read_triangle_mesh(str(path))
    except (RuntimeError, ValueError, OSError):
        raise ck.fail(f"{pre}.file", f"expected a triangle mesh Open3D can read: {fname}") \
            from None
    v0 = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    if t.shape[0] == 0:
        raise ck.fail(f"{pre}.file", f"expected a triangle mesh Open3D can read, found no "
                                     f"triangles in {path}")
    v = (scale * v0) @ R.T + trans
    return v, t, {"file": str(path), "scale": scale, "translation": trans, "rotation": R}


def _confined_mesh_path(fname: str, base_dir: Path, ck, fld: str) -> Path:
    """``fname`` resolved against the scene's folder and confined to it.

    Absolute paths and paths that leave the folder (``../``, symbolic links
    pointing out) are refused with :class:`~mems_stereo.errors.UnsafeFileError`
    unless ``--allow-external`` (:func:`mems_stereo.util.limits.allow_external`);
    the refusal does not tell whether such a file exists.
    """
    from mems_stereo.errors import UnsafeFileError
    from mems_stereo.util.limits import allow_external

    path = Path(fname) if os.path.isabs(fname) else Path(base_dir) / fname
    if allow_external():
        return path
    root = os.path.realpath(base_dir)
    real = os.path.realpath(path)
    if os.path.isabs(fname) or os.path.commonpath([root, real]) != root:
        raise UnsafeFileError("expected a mesh path inside the scene's folder, found "
                              f"{fname!r} (--allow-external to read it)", ck.source, fld)
    return path


def scene_from_dict(d: Any, source: str = "<dict>", base_dir: str | os.PathLike = ".") -> Scene:
    """Build and validate a :class:`Scene` from its JSON object.

    Raises :class:`~mems_stereo.errors.FormatError` naming ``source`` and the
    field, e.g. ``scene.json: objects[2].radius: expected a positive number, found -1``.
    """
    ck = _Checker(source)
    if not isinstance(d, dict):
        raise ck.fail("(top level)", f"expected a JSON object, found {type(d).__name__}")
    check_schema(d, SCENE_FIELDS, ck)  # format, version, members and types
    if "format" in d and d["format"] != SCENE_FORMAT:
        raise ck.fail("format", f"expected {SCENE_FORMAT!r}, found {json.dumps(d['format'])}")
    if "version" in d and d["version"] != SCENE_VERSION:
        raise ck.fail("version", f"expected {SCENE_VERSION}, found {json.dumps(d['version'])}")
    objs = ck.req(d, "objects", "")
    if not isinstance(objs, list) or not objs:
        raise ck.fail("objects", f"expected a non-empty list of objects, found {json.dumps(objs)}")
    name = d.get("name", "")
    objects = [_object_from_dict(o, i, ck, Path(base_dir)) for i, o in enumerate(objs)]
    return Scene(objects, name=str(name), source=source)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene JSON file (mesh paths are relative to its folder)."""
    p = Path(path)
    d = read_json_file(p)
    return scene_from_dict(d, source=str(p), base_dir=p.parent)
