"""Moving scenes: objects with a velocity and an angular rate, ray cast at each shot's time.

A scene object may carry ``velocity`` (3 numbers, m/s, world frame) and ``angular_rate``
(3 numbers, rad/s, a rotation vector's rate about the object's ``center``, or a mesh's
``translation``).  Its geometry as written in the scene is its pose at time 0 of the
recording's clock (the shot times); at time t a vertex x0 is at

    x(t) = R(ω·t)·(x0 − c) + c + v·t        (R: the rotation by the vector ω·t)

:class:`MovingScene` casts rays at one time :attr:`~MovingScene.time` without
rebuilding any geometry: the static objects share one ray-casting scene, and each moving
object is cast in its own body frame (the ray moved by the inverse motion; distances are
kept, normals turned back).  The simulator (:func:`returns_over_time`) casts each slice
of :data:`MOTION_STEP` of shots at the slice's mean time, so the truth (``/truth/point``)
is the scene at each shot's time; :func:`true_ranges_at` and :func:`surface_distance_at`
score points against the scene at each point's own time.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mems_stereo.sim.scene import RayHits, Scene

#: s: the simulator's time slice for moving scenes (0.8 m/s moves 0.4 mm within ±½ ms)
MOTION_STEP = 1e-3


@dataclass(frozen=True, slots=True)
class Motion:
    """Rigid motion of one object: velocity (3,) m/s, angular_rate (3,) rad/s about
    pivot (3,) m, world frame; the pose at time 0 is the object's as written."""

    velocity: np.ndarray
    angular_rate: np.ndarray
    pivot: np.ndarray

    def rotation(self, t: float) -> np.ndarray:
        """(3, 3) R(ω·t)."""
        if not np.any(self.angular_rate):
            return np.eye(3)
        return Rotation.from_rotvec(np.asarray(self.angular_rate) * float(t)).as_matrix()

    def to_body(self, x: np.ndarray, t: float) -> np.ndarray:
        """World points (N, 3) at time t → the object's pose at time 0."""
        R = self.rotation(t)
        return (np.asarray(x, np.float64) - self.pivot - self.velocity * t) @ R + self.pivot

    def apply(self, x0: np.ndarray, t: float) -> np.ndarray:
        """Points (N, 3) of the pose at time 0 → world points at time t."""
        R = self.rotation(t)
        return (np.asarray(x0, np.float64) - self.pivot) @ R.T + self.pivot + self.velocity * t


def motion_of(obj) -> Motion | None:
    """The :class:`Motion` of a scene object (None: it stands still)."""
    v = np.asarray(obj.params.get("velocity", np.zeros(3)), np.float64)
    w = np.asarray(obj.params.get("angular_rate", np.zeros(3)), np.float64)
    if not (np.any(v) or np.any(w)):
        return None
    pivot = obj.params.get("center", obj.params.get("translation", np.zeros(3)))
    return Motion(v, w, np.asarray(pivot, np.float64))


class MovingScene(Scene):
    """A :class:`Scene` with moving objects, cast at the time :attr:`time` (s).

    :meth:`at` gives the same scene at another time (sharing every ray-casting scene).
    """

    def __init__(self, objects, name: str = "", source: str = "<memory>", time: float = 0.0):
        super().__init__(objects, name, source)
        self.time = float(time)
        motions = [motion_of(o) for o in self.objects]
        static = [i for i, m in enumerate(motions) if m is None]
        self._static = (Scene([self.objects[i] for i in static]), np.array(static, np.int64))
        self._moving = [(i, Scene([self.objects[i]]), m) for i, m in enumerate(motions)
                        if m is not None]

    def at(self, t: float) -> MovingScene:
        """This scene at time ``t`` (s, the recording's clock)."""
        out = copy.copy(self)
        out.time = float(t)
        return out

    def cast(self, origins, directions) -> RayHits:
        """First hit of each ray at :attr:`time` (as :meth:`Scene.cast`)."""
        d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), d.shape)
        sc, idx = self._static
        best = sc.cast(o, d)
        best.object_index = np.where(best.object_index >= 0,
                                     idx[np.maximum(best.object_index, 0)] if idx.size else -1,
                                     -1)
        for i, part, m in self._moving:
            R = m.rotation(self.time)
            h = part.cast(m.to_body(o, self.time), d @ R)
            take = h.t < best.t
            if np.any(take):
                best.t[take] = h.t[take]
                best.normal[take] = h.normal[take] @ R.T
                best.point[take] = o[take] + h.t[take, None] * d[take]
                best.object_index[take] = i
        return best

    def surface_distance(self, points) -> np.ndarray:
        """(N,) float64 m: each point's distance to the nearest surface at :attr:`time`."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        dist = np.full(p.shape[0], np.inf)
        parts = [(self._static[0], None)] + [(s, m) for _, s, m in self._moving]
        for sc, m in parts:
            if sc.objects and p.shape[0]:
                q = p if m is None else m.to_body(p, self.time)
                dist = np.minimum(dist, _distance(sc, q))
        return dist


def _distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Distances (N,) m of ``points`` to the triangles of ``scene``'s objects."""
    import open3d as o3d

    caster = getattr(scene, "distance_caster", None)
    if caster is None:  # built once per scene part (Open3D, float32 geometry)
        caster = o3d.t.geometry.RaycastingScene()
        for ob in scene.objects:
            caster.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(ob.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(ob.triangles, dtype=np.uint32)))
        scene.distance_caster = caster
    q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return caster.compute_distance(q).numpy().astype(np.float64)


def as_moving(scene: Scene) -> Scene:
    """``scene`` as a :class:`MovingScene` where any object moves, else unchanged."""
    if isinstance(scene, MovingScene) or all(motion_of(o) is None for o in scene.objects):
        return scene
    return MovingScene(scene.objects, scene.name, scene.source)


def time_slices(times: np.ndarray, step: float = MOTION_STEP) -> list[slice]:
    """Consecutive slices of ``times`` (s, increasing) within one ``step`` each."""
    t = np.asarray(times, np.float64)
    if not t.size:
        return []
    key = np.floor((t - t[0]) / step).astype(np.int64)
    cuts = np.flatnonzero(np.diff(key)) + 1
    edges = np.concatenate([[0], cuts, [t.size]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def returns_over_time(returns: Callable[[Scene, np.ndarray], dict], scene: Scene,
                      times: np.ndarray, theta: np.ndarray) -> dict:
    """``returns(scene, theta)`` (the simulator's per-shot geometry, a dict of per-shot
    arrays) of shots at ``times``: a static scene in one call, a moving one slice by
    slice (:func:`time_slices`) at each slice's mean time."""
    if not isinstance(scene, MovingScene):
        return returns(scene, theta)
    parts = [returns(scene.at(float(np.mean(times[s]))), theta[s])
             for s in time_slices(times)]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _grouped(scene: MovingScene, times: np.ndarray, fn, n: int, width: int = 1) -> np.ndarray:
    """``fn(scene at t, index)`` over the points grouped by slices of :data:`MOTION_STEP`
    of their times (each group at its points' mean time); (n,) or (n, width) float64."""
    out = np.zeros((n, width))
    if not n:
        return out[:, 0] if width == 1 else out
    t = np.asarray(times, np.float64)
    key = np.floor(t / MOTION_STEP)
    for kv in np.unique(key):
        sel = np.flatnonzero(key == kv)
        out[sel] = np.asarray(fn(scene.at(float(t[sel].mean())), sel)).reshape(sel.size, -1)
    return out[:, 0] if width == 1 else out


@dataclass(frozen=True, slots=True)
class TrueHits:
    """The scene's first surface on the ray through each point, at the point's time:
    range (N,) float64 m (inf: none), object (N,) int64 (−1: none)."""

    range: np.ndarray
    object: np.ndarray


def true_hits_at(scene: Scene, points, times) -> TrueHits:
    """:class:`TrueHits` of the rays from the origin (the receiver's projection centre)
    through ``points`` (N, 3) m, in the scene at each point's time ``times`` (N,) s
    (a static scene: any time)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not p.shape[0]:
        return TrueHits(np.zeros(0), np.zeros(0, np.int64))
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    ms = scene if isinstance(scene, MovingScene) else MovingScene(scene.objects)

    def hits(sc, sel):
        h = sc.cast(np.zeros(3), d[sel])
        return np.stack([h.t, h.object_index.astype(np.float64)], axis=1)

    out = _grouped(ms, times, hits, p.shape[0], 2)
    return TrueHits(out[:, 0], out[:, 1].astype(np.int64))


def surface_distance_at(scene: Scene, points, times) -> np.ndarray:
    """(N,) float64 m: each point's distance to the nearest surface at its time."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    ms = scene if isinstance(scene, MovingScene) else MovingScene(scene.objects)
    return _grouped(ms, times, lambda sc, sel: sc.surface_distance(p[sel]), p.shape[0])
