"""Renders people want to look at: hardware at its pose, ground grid and scale, colour bar, σ."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mems_stereo.viz.colormap import apply_colormap
from mems_stereo.viz.render import render_available, render_cloud, render_image
from mems_stereo.viz.render_decorations import Decorations, nice_step, sigma_axes

from mems_stereo.cli import main as cli_main
from mems_stereo.errors import FormatError
from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.cloud import PointCloud

_OK, _WHY = render_available()
needs_gl = pytest.mark.skipif(not _OK, reason=f"headless OpenGL unavailable: {_WHY}")
W, H = 480, 360


def _wall(n=3000, seed=1):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-1.0, 1.0, n), rng.uniform(-0.6, 0.3, n), rng.uniform(2.9, 3.1, n)]
    r = np.linalg.norm(pts, axis=1)
    return PointCloud(pts, {"range": r, "sigma_r": np.full(n, 0.02),
                            "sigma_phi": np.full(n, 2e-3)})


def _camera():
    """Looking at the scene from above and behind (y down: the camera sits at y < 0)."""
    a = np.radians(40.0)
    R = np.array([[1.0, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    c = np.array([0.0, -2.2, -1.5])
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, -R @ c
    K = np.array([[300.0, 0, W / 2 - 0.5], [0, 300.0, H / 2 - 0.5], [0, 0, 1]])
    return K, E


def _project(p, cam):
    K, E = cam
    rvec, _ = cv2.Rodrigues(E[:3, :3])
    return cv2.projectPoints(np.atleast_2d(np.asarray(p, float)), rvec, E[:3, 3], K,
                             None)[0].reshape(-1, 2)


def test_nice_step_and_sigma_axes():
    assert nice_step(10.0) == 1.0 and nice_step(3.0) == 0.5 and nice_step(0.15) == 0.02
    P = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 4.0]])
    ax = sigma_axes(P, [0.01, 0.02], [1e-3, 2e-3])
    # first axis along the receiver ray with length σ_r, second across it in x–z: σ_φ·r
    np.testing.assert_allclose(ax[0, 0], [0, 0, 0.01])
    np.testing.assert_allclose(ax[1, 0], 0.02 * P[1] / 5.0)
    np.testing.assert_allclose(np.linalg.norm(ax[1, 1]), 2e-3 * 5.0)
    assert abs(ax[1, 1] @ P[1]) < 1e-12 and ax[1, 1][1] == 0.0
    # the three axes are orthogonal: a proper ellipsoid
    G = ax[1] @ ax[1].T
    assert np.allclose(G - np.diag(np.diag(G)), 0.0, atol=1e-15)


@needs_gl
def test_hardware_grid_and_colour_bar_land_where_expected():
    cloud, cam, sysm = _wall(), _camera(), burkard2022()
    plain = render_image(cloud, "range", W, H, camera=cam, point_size=2)
    deco = Decorations(system=sysm)
    img = render_image(cloud, "range", W, H, camera=cam, point_size=2, decorations=deco)
    # the scanner block (red) is drawn at the mirror pivot's projection
    u, v = np.rint(_project(sysm.scanner.position, cam)[0]).astype(int)
    patch = img[v - 3:v + 4, u - 3:u + 4].reshape(-1, 3).astype(int)
    assert ((patch[:, 0] > 120) & (patch[:, 1] < 90) & (patch[:, 2] < 90)).any()
    # the receiver frustum (blue) at the origin's projection
    u, v = np.rint(_project([0.0, 0.0, 0.02], cam)[0]).astype(int)
    patch = img[v - 3:v + 4, u - 3:u + 4].reshape(-1, 3).astype(int)
    assert ((patch[:, 2] > 150) & (patch[:, 0] < 120)).any()
    # a grid line (grey) where the floor line x = 0, y = y_max crosses z = 1 m projects
    u, v = np.rint(_project([0.0, cloud.points[:, 1].max(), 1.0], cam)[0]).astype(int)
    patch = img[v - 2:v + 3, u - 2:u + 3].reshape(-1, 3).astype(int)
    grey = (np.abs(patch - 158) < 30).all(axis=1)
    assert grey.any() and not (plain[v - 2:v + 3, u - 2:u + 3] != 255).any()
    # the colour bar: a vertical strip whose ends are the colormap's ends
    x, y0, bh = W - int(0.09 * W) - 3, int(0.2 * H), int(0.6 * H)
    t = np.linspace(1.0, 0.0, bh)
    for row in (2, bh // 2, bh - 3):
        np.testing.assert_allclose(img[y0 + row, x], np.rint(apply_colormap([t[row]])[0] * 255),
                                   atol=1)
    # the legend names the grid's spacing: 0.5 m for this wall
    assert deco.geometry(cloud, np.zeros((len(cloud), 3))).grid_step == 0.5


@needs_gl
def test_ellipsoids_grow_with_sigma(tmp_path):
    cam = _camera()
    counts = []
    for s in (0.001, 0.05):
        c = _wall(200)
        c.attributes["sigma_r"] = np.full(200, s)
        img = render_image(c, "range", W, H, camera=cam, point_size=1,
                           decorations=Decorations(grid=False, colorbar=False, ellipsoids=True,
                                                   n_sigma=3.0))
        counts.append(int((img != 255).any(axis=2).sum()))
    assert counts[1] > 1.5 * counts[0]
    bare = PointCloud(np.ones((3, 3)), {"range": np.ones(3)})
    with pytest.raises(FormatError, match="sigma_r"):
        render_image(bare, decorations=Decorations(ellipsoids=True))


@needs_gl
def test_cli_render_decorated(tmp_path):
    from mems_stereo.viz.export import write_cloud

    write_cloud(tmp_path / "w.ply", _wall(500))
    out = tmp_path / "w.png"
    assert cli_main(["render", str(tmp_path / "w.ply"), "-o", str(out), "--view", "oblique",
                     "--system", "burkard2022", "--ellipsoids", "2", "--width", "320",
                     "--height", "240"]) == 0
    png = cv2.imread(str(out))
    assert png.shape == (240, 320, 3) and (png != 255).any(axis=2).mean() > 0.02
    render_cloud(_wall(50), tmp_path / "v.png", width=64, height=48,
                 decorations=Decorations())
