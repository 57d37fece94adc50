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
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from mems_stereo.viz.colormap import ColorScale, cloud_colors
from mems_stereo.viz.render_decorations import DecorationGeometry, Decorations, Extra

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


def render_image(cloud: PointCloud, color_by: str = "range", width: int = 1280,
                 height: int = 960, view: str = "camera", camera=None,
                 point_size: float = 3.0, background=(1.0, 1.0, 1.0),
                 scale: ColorScale | None = None,
                 decorations: Decorations | None = None) -> np.ndarray:
    """Render ``cloud`` offscreen; returns the image (height, width, 3) uint8 RGB.

    ``color_by``: an attribute name or x/y/z (see :func:`mems_stereo.viz.colormap.cloud_colors`),
    coloured through ``scale`` (:class:`~mems_stereo.viz.colormap.ColorScale`: colormap and
    the values at its ends; default ``turbo`` between the 2nd and 98th percentile);
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
    scale = ColorScale() if scale is None else scale
    colors = cloud_colors(cloud, color_by, scale.cmap, scale.vmin, scale.vmax)
    pts = cloud.points
    keep = np.isfinite(pts).all(axis=1)
    pts, colors = pts[keep], colors[keep]
    deco = DecorationGeometry([], pts, 0.0)
    if decorations is not None:
        deco = decorations.geometry(cloud.select(keep), colors)
    extras = deco.extras
    if camera is None:
        K, E = view_camera(deco.frame_points, view, width, height)
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
        img = decorations.overlay(img, cloud, color_by, scale, deco.grid_step)
    return img


def render_cloud(cloud: PointCloud, path: str | os.PathLike, color_by: str = "range",
                 width: int = 1280, height: int = 960, view: str = "camera", camera=None,
                 **kwargs) -> Path:
    """Render ``cloud`` offscreen and write a PNG atomically; returns the path.

    Same parameters as :func:`render_image` (``point_size``, ``background``,
    ``scale``, ``decorations`` as keywords).
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
