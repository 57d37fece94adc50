"""Colormaps, view placement and the headless Open3D render (Mesa EGL)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mems_stereo.viz.colormap import COLORMAPS, NAN_COLOR, apply_colormap, cloud_colors, normalize
from mems_stereo.viz.render import (
    VIEWS,
    render_available,
    render_cloud,
    render_image,
    view_camera,
)

from mems_stereo.errors import FormatError
from mems_stereo.pipeline.cloud import PointCloud

_OK, _WHY = render_available()
needs_gl = pytest.mark.skipif(not _OK, reason=f"headless OpenGL unavailable: {_WHY}")


@pytest.mark.parametrize("name", sorted(COLORMAPS))
def test_colormap_matches_matplotlib(name):
    import matplotlib

    t = np.linspace(0, 1, 1001)
    ref = matplotlib.colormaps[name](t)[:, :3]
    assert np.abs(apply_colormap(t, name) - ref).max() < 0.025


def test_colormap_edges():
    rgb = apply_colormap(np.array([-1.0, 2.0, np.nan]), "viridis")
    np.testing.assert_allclose(rgb[0], apply_colormap([0.0], "viridis")[0])
    np.testing.assert_allclose(rgb[1], apply_colormap([1.0], "viridis")[0])
    np.testing.assert_allclose(rgb[2], NAN_COLOR)
    with pytest.raises(FormatError, match="colormap"):
        apply_colormap([0.5], "jet")


def test_normalize():
    v = np.arange(101.0)
    np.testing.assert_allclose(normalize(v), (v - 2) / 96)  # 2nd..98th percentile
    np.testing.assert_allclose(normalize(v, 0, 50), v / 50)
    assert np.all(normalize(np.full(4, 3.0)) == 0.5)
    assert np.isnan(normalize(np.array([1.0, np.nan, 2.0]))[1])


def test_cloud_colors_by_attribute_and_axis():
    c = PointCloud(np.c_[np.zeros(3), np.zeros(3), [1.0, 2.0, 3.0]], {"range": [1.0, 2, 3]})
    np.testing.assert_allclose(cloud_colors(c, "z", vmin=1, vmax=3),
                               apply_colormap([0, 0.5, 1]))
    np.testing.assert_allclose(cloud_colors(c, "range", vmin=1, vmax=3),
                               cloud_colors(c, "z", vmin=1, vmax=3))
    with pytest.raises(FormatError, match="sigma_r"):
        cloud_colors(c, "sigma_r")


@pytest.mark.parametrize("view", VIEWS)
def test_view_camera_frames_every_point(view):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 2, 300), rng.uniform(-0.4, 0.1, 300), rng.uniform(1, 6, 300)]
    w, h = 640, 480
    K, E = view_camera(pts, view, w, h)
    rvec, _ = cv2.Rodrigues(E[:3, :3])
    uv = cv2.projectPoints(pts, rvec, E[:3, 3], K, None)[0].reshape(-1, 2)
    depth = pts @ E[:3, :3].T + E[:3, 3]
    assert np.all(depth[:, 2] > 0)
    assert np.all((uv >= 0) & (uv <= [w - 1, h - 1]))
    if view == "camera":  # receiver viewpoint: the farthest ray reaches 90 % of the half-width
        np.testing.assert_allclose(np.abs((uv - K[:2, 2]) / [w / 2, h / 2]).max(), 0.9)
    else:  # the cloud fills a good part of the image, not a speck
        span = uv.max(axis=0) - uv.min(axis=0)
        assert max(span[0] / w, span[1] / h) > 0.6


def test_camera_must_be_centred_square_pixels():
    cloud, (K, E), w, h = _plane_scene()
    for bad in (np.diag([200.0, 300.0, 1.0]), K + [[0, 0, 5], [0, 0, 0], [0, 0, 0]]):
        bad = bad.copy()
        bad[:2, 2] = K[:2, 2] if bad[0, 0] != bad[1, 1] else bad[:2, 2]
        with pytest.raises(FormatError, match="principal point"):
            render_image(cloud, "counts", w, h, camera=(bad, E))


def test_bad_view_and_size():
    c = PointCloud(np.ones((3, 3)), {"range": np.ones(3)})
    with pytest.raises(FormatError, match="view"):
        render_image(c, view="under")
    with pytest.raises(FormatError, match="size"):
        render_image(c, width=4, height=4)


def _plane_scene():
    """A dense plane patch at z = 3 m and a camera that sees it off-centre."""
    rng = np.random.default_rng(42)
    n = 40000
    pts = np.c_[rng.uniform(0.2, 0.8, n), rng.uniform(-0.5, 0.1, n), np.full(n, 3.0)]
    cloud = PointCloud(pts, {"counts": np.full(n, 7, np.int32), "range": np.linalg.norm(pts, axis=1)})
    w, h = 320, 240
    K = np.array([[200.0, 0, w / 2 - 0.5], [0, 200.0, h / 2 - 0.5], [0, 0, 1]])
    return cloud, (K, np.eye(4)), w, h


@needs_gl
def test_render_plane_lands_where_projected():
    cloud, cam, w, h = _plane_scene()
    img = render_image(cloud, color_by="counts", width=w, height=h, camera=cam, point_size=2)
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    # where the patch should be, by OpenCV's projection of its corners
    corners = np.array([[0.2, -0.5, 3], [0.8, 0.1, 3]])
    uv = cv2.projectPoints(corners, np.zeros(3), np.zeros(3), cam[0], None)[0].reshape(-1, 2)
    (u0, v0), (u1, v1) = uv
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    inside = (uu > u0 + 3) & (uu < u1 - 3) & (vv > v0 + 3) & (vv < v1 - 3)
    outside = (uu < u0 - 3) | (uu > u1 + 3) | (vv < v0 - 3) | (vv > v1 + 3)
    drawn = (img != 255).any(axis=2)
    assert drawn[inside].mean() > 0.99
    assert not drawn[outside].any()
    # a constant attribute maps to the middle of the colormap, unlit
    expect = np.rint(apply_colormap([0.5])[0] * 255)
    np.testing.assert_allclose(np.median(img[inside], axis=0), expect, atol=2)


@needs_gl
def test_render_cloud_writes_png(tmp_path):
    cloud, cam, w, h = _plane_scene()
    out = render_cloud(cloud, tmp_path / "v.png", color_by="range", width=w, height=h,
                       view="oblique")
    png = cv2.imread(str(out))
    assert png.shape == (h, w, 3)
    assert 0.01 < (png != 255).any(axis=2).mean() < 0.95  # neither blank nor flooded
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.png"]
    with pytest.raises(FormatError, match="png"):
        render_cloud(cloud, tmp_path / "v.jpg")


@needs_gl
def test_subprocess_fallback(monkeypatch):
    import mems_stereo.viz.render as r

    cloud, cam, w, h = _plane_scene()
    direct = render_image(cloud, "counts", w, h, camera=cam)
    monkeypatch.setattr(r, "_render_array", lambda *a: None)  # in-process context fails
    via_subprocess = render_image(cloud, "counts", w, h, camera=cam)
    assert np.mean(direct != via_subprocess) < 0.01


def test_no_context_gives_clear_error(monkeypatch):
    import mems_stereo.viz.render as r

    monkeypatch.setattr(r, "_render_array", lambda *a: None)
    monkeypatch.setattr(r, "_render_in_subprocess", lambda *a: None)
    cloud, cam, w, h = _plane_scene()
    with pytest.raises(r.RenderUnavailableError, match="libegl1"):
        render_image(cloud, "counts", w, h, camera=cam)


def test_empty_cloud_renders_background():
    img = render_image(PointCloud(np.zeros((0, 3)), {"range": np.zeros(0)}), width=32,
                       height=16, background=(0.0, 0.0, 1.0))
    assert img.shape == (16, 32, 3) and np.all(img == [0, 0, 255])


def test_view_without_display(monkeypatch):
    from mems_stereo.viz.view import DisplayUnavailableError, view_cloud

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(DisplayUnavailableError, match="mems-stereo render"):
        view_cloud(PointCloud(np.ones((2, 3)), {"range": np.ones(2)}))
