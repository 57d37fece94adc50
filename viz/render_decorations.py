"""What :func:`mems_stereo.viz.render.render_image` draws besides the points.

:class:`Decorations` says what (the receiver and scanner at their poses, a
ground grid, the colour bar, σ ellipsoids); it turns into :class:`Extra`
geometry (line sets and triangle meshes, world frame, m) before the render
and into an overlay on the rendered image after it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from mems_stereo.viz.colormap import ColorScale, apply_colormap

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud


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


@dataclass(frozen=True, slots=True)
class DecorationGeometry:
    """What :meth:`Decorations.geometry` adds to a render.

    extras : the line sets and meshes drawn with the points (world frame, m).
    frame_points : (M, 3) float64, m: the points the placed views frame (the
        cloud's, the origin, the scanner and the ellipsoids' vertices).
    grid_step : the ground grid's spacing, m (0.0 without a grid).
    """

    extras: list[Extra]
    frame_points: np.ndarray
    grid_step: float


@dataclass
class Decorations:
    """What :func:`render_image` draws besides the points.

    Attributes
    ----------
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

    def geometry(self, cloud: PointCloud, colors: np.ndarray) -> DecorationGeometry:
        """The geometry drawn with the cloud (finite points only; ``colors`` (N, 3) its
        points' colours in [0, 1]) and the points the camera frames."""
        grid_step = 0.0
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
            grid_step = step
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
        return DecorationGeometry(extras, np.concatenate(frame), grid_step)

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

    def overlay(self, img: np.ndarray, cloud: PointCloud, color_by: str, scale: ColorScale,
                grid_step: float) -> np.ndarray:
        """Draw the colour bar, the grid's scale (``grid_step`` m, from :meth:`geometry`)
        and a legend onto the RGB image (H, W, 3) uint8."""
        import cv2

        vmin, vmax, cmap = scale.vmin, scale.vmax, scale.cmap
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
        if self.grid and grid_step:
            lines.append((f"ground grid: {grid_step:g} m", GRID_COLOR))
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
