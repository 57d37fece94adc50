"""Headless rendering of point clouds to PNG with Open3D's legacy visualiser.

How it works on a machine with no GPU and no display: a hidden
``open3d.visualization.Visualizer`` window falls back to an EGL offscreen
context from Mesa (llvmpipe, software rasterisation); Debian packages
``libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri`` (installed by
``scripts/setup.sh``).  The Filament ``OffscreenRenderer`` is not used: it
needs Vulkan and aborts the whole process without it.  When a hidden window
cannot be opened in this process (for example after a Filament renderer was
created in it) the render is retried once in a fresh Python subprocess.

The camera is an OpenCV pinhole (x right, y down, z forward, as the world
frame): :func:`view_camera` places it for the named views, or pass your own
``camera=(K, extrinsic)``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mems_stereo.viz.colormap import cloud_colors

from mems_stereo.errors import FormatError, MemsStereoError
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.util.atomic import atomic_output

VIEWS = ("camera", "top", "side", "oblique")
#: Debian packages the offscreen path needs
RENDER_PACKAGES = "libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri"
_HFOV = np.radians(50.0)  # horizontal field of view of the placed views


class RenderUnavailableError(MemsStereoError):
    """No OpenGL context could be created (neither a display nor Mesa EGL)."""


def _rotation(view: str) -> np.ndarray:
    """World → camera rotation (rows are the camera's x, y, z axes in the world)."""
    if view == "camera":
        return np.eye(3)
    if view == "top":  # from above (−y), looking down +y; image up = +z (far)
        return np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    if view == "side":  # from +x looking along −x; image right = +z (far)
        return np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]])
    if view == "oblique":  # from behind and above, pitched 35° down
        a = np.radians(35.0)
        return np.array([[1.0, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    raise FormatError(f"unknown view {view!r}; expected one of {VIEWS}", field="view")


def view_camera(points, view: str = "camera", width: int = 1280,
                height: int = 960) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole camera that shows all ``points`` (N, 3) m, world frame.

    ``camera``: at the receiver's projection centre looking along +z, focal
    length chosen so every point ahead fits; ``top``, ``side``, ``oblique``: a
    50° horizontal field of view, moved back until the cloud fits with a margin.
    Returns ``K`` (3, 3) float64 pixels (principal point at the image centre)
    and ``extrinsic`` (4, 4) float64 world → camera.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    R = _rotation(view)
    half = np.array([width / 2.0, height / 2.0]) * 0.9
    if pts.shape[0] == 0:
        pts = np.array([[0.0, 0.0, 1.0]])
    if view == "camera":
        c = np.zeros(3)
        ahead = pts[pts[:, 2] > 1e-9]
        if ahead.shape[0]:
            tan = np.abs(ahead[:, :2] / ahead[:, 2:3]).max(axis=0)
            with np.errstate(divide="ignore"):
                f = float(np.min(np.where(tan > 0, half / tan, np.inf)))
            f = f if np.isfinite(f) else float(half[0])
        else:
            f = float(half[0])
    else:
        f = width / 2.0 / np.tan(_HFOV / 2)
        q = pts @ R.T
        lo, hi = q.min(axis=0), q.max(axis=0)
        mid = (lo + hi) / 2
        ext = np.maximum(hi - lo, 1e-6)
        dist = max(ext[0] / 2 * f / half[0], ext[1] / 2 * f / half[1], 0.05 * ext[2], 1e-3)
        c = R.T @ np.array([mid[0], mid[1], lo[2] - dist])
    K = np.array([[f, 0.0, width / 2.0 - 0.5], [0.0, f, height / 2.0 - 0.5], [0.0, 0.0, 1.0]])
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = -R @ c
    return K, E


def _quiet_glfw_env() -> None:
    # GLFW probes Wayland and prints "XDG_RUNTIME_DIR is invalid" when it is unset.
    if not os.environ.get("XDG_RUNTIME_DIR"):
        os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="mems-stereo-xdg-")


def _render_array(points, colors, width, height, K, E, point_size, background, extras=()):
    """(H, W, 3) uint8 image, or None when no OpenGL context could be made.

    ``extras`` : list of :class:`Extra` (line sets and triangle meshes) drawn too.
    """
    import open3d as o3d

    _quiet_glfw_env()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        vis = o3d.visualization.Visualizer()
        if not vis.create_window(window_name="mems-stereo", width=width, height=height,
                                 visible=False):
            return None
        try:
            pc = o3d.geometry.PointCloud()
            pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, np.float64))
            pc.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(colors, np.float64))
            vis.add_geometry(pc)
            for ex in extras:
                vis.add_geometry(ex.to_open3d())
            opt = vis.get_render_option()
            opt.mesh_show_back_face = True
            opt.point_size = float(point_size)
            opt.background_color = np.asarray(background, dtype=np.float64)
            par = o3d.camera.PinholeCameraParameters()
            par.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, K)
            par.extrinsic = E
            vis.get_view_control().convert_from_pinhole_camera_parameters(
                par, allow_arbitrary=True)
            vis.poll_events()
            vis.update_renderer()
            buf = np.asarray(vis.capture_screen_float_buffer(do_render=True))
        finally:
            vis.destroy_window()
    return np.clip(np.rint(buf * 255.0), 0, 255).astype(np.uint8)


def _render_in_subprocess(points, colors, width, height, K, E, point_size, background,
                          extras=()):
    with tempfile.TemporaryDirectory(prefix="mems-stereo-render-") as d:
        src, out = Path(d) / "in.npz", Path(d) / "out.npy"
        ex = {}
        for i, e in enumerate(extras):
            ex[f"extra{i}_{e.kind}_v"], ex[f"extra{i}_{e.kind}_i"] = e.vertices, e.indices
            ex[f"extra{i}_{e.kind}_c"] = e.colors
        np.savez(src, points=points, colors=colors, K=K, E=E, **ex)
        opts = json.dumps({"width": width, "height": height, "point_size": point_size,
                           "background": list(map(float, background))})
        proc = subprocess.run([sys.executable, "-m", "mems_stereo.viz.render", str(src), str(out),
                               opts],
                              capture_output=True, text=True, timeout=300)
        if proc.returncode != 0 or not out.exists():
            return None
        return np.load(out)


@dataclass
class Extra:
    """A line set (``kind="lines"``: vertices (n, 3), indices (m, 2)) or a triangle mesh
    (``"mesh"``: indices (m, 3)) with per-vertex colours (n, 3) in [0, 1], world frame, m."""

    kind: str
    vertices: np.ndarray
    indices: np.ndarray
    colors: np.ndarray

    def to_open3d(self):
        import open3d as o3d

        v = o3d.utility.Vector3dVector(np.ascontiguousarray(self.vertices, np.float64))
        c = o3d.utility.Vector3dVector(np.ascontiguousarray(self.colors, np.float64))
        if self.kind == "lines":
            g = o3d.geometry.LineSet(v, o3d.utility.Vector2iVector(
                np.ascontiguousarray(self.indices, np.int32)))
            # LineSet colours are per line: the colour of each line's first vertex
            g.colors = o3d.utility.Vector3dVector(
                np.ascontiguousarray(np.asarray(self.colors)[self.indices[:, 0]], np.float64))
            return g
        g = o3d.geometry.TriangleMesh(v, o3d.utility.Vector3iVector(
            np.ascontiguousarray(self.indices, np.int32)))
        g.vertex_colors = c
        g.compute_vertex_normals()
        return g


RECEIVER_COLOR = (0.10, 0.30, 0.90)
SCANNER_COLOR = (0.85, 0.10, 0.10)
GRID_COLOR = (0.62, 0.62, 0.62)
_UNITS = {"range": "m", "x": "m", "y": "m", "z": "m", "sigma_r": "m", "sigma_phi": "rad",
          "pixel": "px", "counts": "counts"}


def nice_step(span: float, n: int = 8) -> float:
    """A 1-2-5 × 10^k step giving about ``n`` intervals over ``span`` (> 0)."""
    raw = max(span, 1e-9) / n
    e = 10.0 ** math.floor(math.log10(raw))
    return float(min((m * e for m in (1, 2, 5, 10)), key=lambda s: abs(s - raw)))


def _box(centre, half, color) -> Extra:
    c = np.asarray(centre, float)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    V = c + corners * np.asarray(half, float)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return Extra("mesh", V, F, np.tile(color, (8, 1)))


def sigma_axes(points, sigma_r, sigma_phi) -> np.ndarray:
    """Semi-axes of the 1σ ellipsoid of each point: (N, 3, 3) rows = axis vectors, m.

    Along the receiver ray u = P/|P|: σ_r; across it in the x–z plane: σ_φ·|P|
    (FORMAT v1 attributes, the paper's Eqs. 16–17); along y: σ_φ·|P| as well (a
    line sensor measures no y, so this only draws the angular spread round).
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.linalg.norm(P, axis=1)
    u = P / np.maximum(r, 1e-12)[:, None]
    v = np.stack([u[:, 2], np.zeros_like(r), -u[:, 0]], axis=1)
    v /= np.maximum(np.linalg.norm(v, axis=1), 1e-12)[:, None]
    w = np.cross(u, v)
    a = np.asarray(sigma_r, float)[:, None]
    b = (np.asarray(sigma_phi, float) * r)[:, None]
    return np.stack([u * a, v * b, w * b], axis=1)


@dataclass
class Decorations:
    """What :func:`render_image` draws besides the points.

    system : a :class:`~mems_stereo.model.system.System`: the receiver (blue
        frustum at the origin, looking along +z) and the scanner (red block at
        the mirror pivot, the mirror plate at θ0, the two extreme beams of the
        scan) at their poses; None: not drawn.
    grid : a ground grid (x–z plane at the floor, y = the cloud's largest y:
        y points down) with a 1-2-5 spacing, written in the image's corner.
    colorbar : the colour scale with its limits and unit, on the right.
    ellipsoids : σ ellipsoids (:func:`sigma_axes`, scaled by ``n_sigma``) of at
        most ``max_ellipsoids`` points (evenly subsampled).
    """

    system: object | None = None
    grid: bool = True
    colorbar: bool = True
    ellipsoids: bool = False
    n_sigma: float = 3.0
    max_ellipsoids: int = 400
    _grid_step: float = 0.0

    def geometry(self, cloud: PointCloud, colors: np.ndarray):
        """``(extras, points_to_frame)`` for the cloud (finite points only)."""
        pts = cloud.points
        extras: list[Extra] = []
        frame = [pts, np.zeros((1, 3))]
        lo = pts.min(axis=0) if len(pts) else np.array([-1.0, 0.0, 0.0])
        hi = pts.max(axis=0) if len(pts) else np.array([1.0, 0.0, 3.0])
        size = float(max(np.max(hi - lo), 0.5))
        if self.system is not None:
            extras += self._hardware(size, max(float(hi[2]), 1.0))
            frame.append(np.asarray(self.system.scanner.position, float)[None])
        if self.grid:
            x0, x1 = min(lo[0], -0.2), max(hi[0], 0.2)
            z0, z1 = 0.0, max(hi[2], 1.0)
            step = nice_step(max(x1 - x0, z1 - z0))
            self._grid_step = step
            xs = np.arange(math.floor(x0 / step), math.ceil(x1 / step) + 1) * step
            zs = np.arange(math.floor(z0 / step), math.ceil(z1 / step) + 1) * step
            yg = float(hi[1]) if len(pts) else 0.5
            V, L = [], []
            for x in xs:
                V += [[x, yg, zs[0]], [x, yg, zs[-1]]]
                L.append([len(V) - 2, len(V) - 1])
            for z in zs:
                V += [[xs[0], yg, z], [xs[-1], yg, z]]
                L.append([len(V) - 2, len(V) - 1])
            V = np.asarray(V)
            extras.append(Extra("lines", V, np.asarray(L), np.tile(GRID_COLOR, (len(V), 1))))
        if self.ellipsoids and len(pts):
            if "sigma_r" not in cloud.attributes or "sigma_phi" not in cloud.attributes:
                raise FormatError("σ ellipsoids need the attributes sigma_r and sigma_phi",
                                  field="ellipsoids")
            idx = np.linspace(0, len(pts) - 1, min(len(pts), self.max_ellipsoids)).astype(int)
            ax = sigma_axes(pts[idx], cloud["sigma_r"][idx], cloud["sigma_phi"][idx])
            ok = np.isfinite(ax).all(axis=(1, 2))
            idx, ax = idx[ok], ax[ok]
            if len(idx):
                sph, tri = _unit_sphere()
                V = pts[idx][:, None, :] + self.n_sigma * np.einsum("vk,nkj->nvj", sph, ax)
                F = tri[None] + (np.arange(len(idx)) * len(sph))[:, None, None]
                C = np.repeat(0.6 * colors[idx], len(sph), axis=0)
                extras.append(Extra("mesh", V.reshape(-1, 3), F.reshape(-1, 3), C))
                frame.append(V.reshape(-1, 3))
        return extras, np.concatenate(frame)

    def _hardware(self, size: float, depth: float) -> list[Extra]:
        sysm = self.system
        s = 0.06 * size
        rc = sysm.receiver
        K = np.asarray(rc.camera_matrix, float)
        w, h = rc.image_size
        tx = (w / 2.0) / K[0, 0]
        ty = max((h / 2.0) / K[1, 1], 0.25 * tx)
        V = np.array([[0, 0, 0], [-tx, -ty, 1], [tx, -ty, 1], [tx, ty, 1], [-tx, ty, 1]]) * s
        F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1], [1, 3, 2], [1, 4, 3]])
        out = [Extra("mesh", V, F, np.tile(RECEIVER_COLOR, (5, 1)))]
        sc = sysm.scanner
        p = np.asarray(sc.position, float)
        e1, e2 = np.asarray(sc.normal_basis, float)
        axis = np.cross(e1, e2)
        out.append(_box(p, [0.25 * s] * 3, SCANNER_COLOR))
        n0 = math.cos(sc.theta0) * e1 + math.sin(sc.theta0) * e2
        t = np.cross(axis, n0)
        m = 0.6 * s
        Vm = p + np.array([t * m + axis * m, -t * m + axis * m, -t * m - axis * m,
                           t * m - axis * m]) - 0.3 * s * n0
        out.append(Extra("mesh", Vm, np.array([[0, 1, 2], [0, 2, 3]]),
                         np.tile([0.75, 0.75, 0.8], (4, 1))))
        dl = np.asarray(sc.laser_direction, float)
        V, L = [], []
        for th in (sc.theta0 - sc.theta_mech_max, sc.theta0 + sc.theta_mech_max):
            n = math.cos(th) * e1 + math.sin(th) * e2
            d = dl - 2.0 * (n @ dl) * n
            V += [p, p + d * depth]
            L.append([len(V) - 2, len(V) - 1])
        out.append(Extra("lines", np.asarray(V), np.asarray(L),
                         np.tile(SCANNER_COLOR, (len(V), 1))))
        return out

    def overlay(self, img: np.ndarray, cloud: PointCloud, color_by: str, cmap: str,
                vmin, vmax) -> np.ndarray:
        """Draw the colour bar, the grid's scale and a legend onto the RGB image."""
        import cv2
        from mems_stereo.viz.colormap import apply_colormap

        out = np.ascontiguousarray(img.copy())
        H, W = out.shape[:2]
        fs = max(0.35, H / 1400.0)
        th = 1
        ink = (30, 30, 30)
        if self.colorbar and len(cloud):
            axes = {"x": 0, "y": 1, "z": 2}
            v = (cloud.attributes[color_by] if color_by in cloud.attributes
                 else cloud.points[:, axes[color_by]])
            v = np.asarray(v, float)
            fin = v[np.isfinite(v)]
            lo = vmin if vmin is not None else (float(np.percentile(fin, 2)) if fin.size else 0)
            hi = vmax if vmax is not None else (float(np.percentile(fin, 98)) if fin.size else 1)
            bh, bw = int(0.6 * H), max(8, W // 60)
            x1, y0 = W - int(0.09 * W), int(0.2 * H)
            x0 = x1 - bw
            t = np.linspace(1.0, 0.0, bh)
            rgb = np.rint(apply_colormap(t, cmap) * 255).astype(np.uint8)
            out[y0:y0 + bh, x0:x1] = rgb[:, None, :]
            cv2.rectangle(out, (x0 - 1, y0 - 1), (x1, y0 + bh), ink, 1)
            unit = _UNITS.get(color_by, "")
            cv2.putText(out, f"{hi:.3g}", (x1 + 4, y0 + 8), cv2.FONT_HERSHEY_SIMPLEX, fs, ink,
                        th, cv2.LINE_AA)
            cv2.putText(out, f"{lo:.3g}", (x1 + 4, y0 + bh), cv2.FONT_HERSHEY_SIMPLEX, fs, ink,
                        th, cv2.LINE_AA)
            cv2.putText(out, f"{color_by}" + (f" ({unit})" if unit else ""),
                        (x0 - int(0.05 * W), y0 - 8), cv2.FONT_HERSHEY_SIMPLEX, fs, ink, th,
                        cv2.LINE_AA)
        lines = []
        if self.grid and self._grid_step:
            lines.append((f"ground grid: {self._grid_step:g} m", GRID_COLOR))
        if self.system is not None:
            lines += [("receiver", RECEIVER_COLOR), ("scanner, scan limits", SCANNER_COLOR)]
        if self.ellipsoids:
            lines.append((f"{self.n_sigma:g} sigma ellipsoids", (0.3, 0.3, 0.3)))
        y = H - 10 - int(22 * fs / 0.5) * (len(lines) - 1)
        for text, col in lines:
            c = tuple(int(255 * x) for x in col)
            cv2.rectangle(out, (10, y - 9), (22, y + 1), c, -1)
            cv2.putText(out, text, (28, y), cv2.FONT_HERSHEY_SIMPLEX, fs, ink, th, cv2.LINE_AA)
            y += int(22 * fs / 0.5)
        return out


def _unit_sphere(res: int = 6):
    """Vertices (n, 3) and triangles (m, 3) of a UV sphere of radius 1."""
    th = np.linspace(0, np.pi, res + 1)
    ph = np.linspace(0, 2 * np.pi, 2 * res, endpoint=False)
    V = np.array([[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]
                  for t in th for p in ph])
    n = len(ph)
    F = []
    for i in range(res):
        for j in range(n):
            a, b = i * n + j, i * n + (j + 1) % n
            c, d = a + n, b + n
            F += [[a, c, b], [b, c, d]]
    return V, np.asarray(F)


def render_image(cloud: PointCloud, color_by: str = "range", width: int = 1280,
                 height: int = 960, view: str = "camera", camera=None,
                 point_size: float = 3.0, background=(1.0, 1.0, 1.0), cmap: str = "turbo",
                 vmin: float | None = None, vmax: float | None = None,
                 decorations: Decorations | None = None) -> np.ndarray:
    """Render ``cloud`` offscreen; returns the image (height, width, 3) uint8 RGB.

    ``color_by``: an attribute name or x/y/z (see :func:`mems_stereo.viz.colormap.cloud_colors`);
    ``view``: one of :data:`VIEWS`, or ``camera=(K (3, 3), extrinsic (4, 4)
    world → camera)`` to set the OpenCV pinhole yourself (fx = fy and the
    principal point at the image centre, ((width-1)/2, (height-1)/2): Open3D's
    legacy view control supports nothing else).  Raises
    RenderUnavailableError when no OpenGL context can be created.
    """
    width, height = int(width), int(height)
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise FormatError(f"image size must be 16..8192 px, found {width} x {height}",
                          field="width/height")
    colors = cloud_colors(cloud, color_by, cmap, vmin, vmax)
    pts = cloud.points
    keep = np.isfinite(pts).all(axis=1)
    pts, colors = pts[keep], colors[keep]
    extras: list = []
    frame_pts = pts
    if decorations is not None:
        extras, frame_pts = decorations.geometry(cloud.select(keep), colors)
    if camera is None:
        K, E = view_camera(frame_pts, view, width, height)
    else:
        K = np.asarray(camera[0], dtype=np.float64).reshape(3, 3)
        E = np.asarray(camera[1], dtype=np.float64).reshape(4, 4)
        centre = (width / 2.0 - 0.5, height / 2.0 - 0.5)
        if not (np.isclose(K[0, 0], K[1, 1]) and np.allclose(K[:2, 2], centre)):
            # Open3D's legacy view control silently ignores anything else
            raise FormatError(f"camera K must have fx == fy and the principal point at the "
                              f"image centre {centre}, found fx = {K[0, 0]:g}, fy = "
                              f"{K[1, 1]:g}, c = {tuple(K[:2, 2])}", field="camera")
    if pts.shape[0] == 0:  # Open3D needs a geometry; an empty cloud renders as background
        bg = np.clip(np.rint(np.asarray(background, dtype=np.float64) * 255), 0, 255)
        return np.broadcast_to(bg.astype(np.uint8), (height, width, 3)).copy()
    args = (pts, colors, width, height, K, E, point_size, tuple(background))
    if extras:
        args = args + (extras,)
    img = _render_array(*args)
    if img is None:
        img = _render_in_subprocess(*args)
    if img is None:
        raise RenderUnavailableError(
            "no OpenGL context for offscreen rendering: Open3D found no display and could not "
            f"open a Mesa EGL context; install the Debian packages {RENDER_PACKAGES} "
            "(scripts/setup.sh does) or run under xvfb-run")
    if decorations is not None:
        img = decorations.overlay(img, cloud, color_by, cmap, vmin, vmax)
    return img


def render_cloud(cloud: PointCloud, path: str | os.PathLike, color_by: str = "range",
                 width: int = 1280, height: int = 960, view: str = "camera", camera=None,
                 **kwargs) -> Path:
    """Render ``cloud`` offscreen and write a PNG atomically; returns the path.

    Same parameters as :func:`render_image` (``point_size``, ``background``,
    ``cmap``, ``vmin``, ``vmax`` as keywords).
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise FormatError(f"expected a .png output, found {path.suffix!r}", source=str(path))
    img = render_image(cloud, color_by, width, height, view, camera, **kwargs)
    import cv2

    with atomic_output(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[:, :, ::-1])):
            raise FormatError("could not write the PNG", source=str(path))
    return path


def render_available() -> tuple[bool, str]:
    """Whether a hidden Open3D window can be opened here, and why not."""
    try:
        import open3d as o3d
    except ImportError as e:
        return False, f"open3d cannot be imported: {e}"
    _quiet_glfw_env()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        vis = o3d.visualization.Visualizer()
        ok = vis.create_window(width=32, height=32, visible=False)
        if ok:
            vis.destroy_window()
    return ok, "" if ok else f"no OpenGL context (need a display or {RENDER_PACKAGES})"


def _main(argv: list[str]) -> int:
    """Worker: ``python -m mems_stereo.viz.render IN.npz OUT.npy OPTIONS_JSON``."""
    src, out, opts = argv[0], argv[1], json.loads(argv[2])
    d = np.load(src)
    extras = []
    i = 0
    while any(f"extra{i}_{k}_v" in d for k in ("lines", "mesh")):
        k = "lines" if f"extra{i}_lines_v" in d else "mesh"
        extras.append(Extra(k, d[f"extra{i}_{k}_v"], d[f"extra{i}_{k}_i"], d[f"extra{i}_{k}_c"]))
        i += 1
    img = _render_array(d["points"], d["colors"], opts["width"], opts["height"], d["K"], d["E"],
                        opts["point_size"], tuple(opts["background"]), extras)
    if img is None:
        return 3
    np.save(out, img)
    return 0


if __name__ == "__main__":  # pragma: no cover - exercised through the fallback
    sys.exit(_main(sys.argv[1:]))
