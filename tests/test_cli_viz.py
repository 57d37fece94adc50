"""The export, view, render and plot commands through mems_stereo.cli.main."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mems_stereo.viz.export import LAS_SCALE, read_cloud, write_cloud
from mems_stereo.viz.render import render_available

from mems_stereo.cli import main
from mems_stereo.io.histograms import write_histograms
from mems_stereo.pipeline.cloud import PointCloud


@pytest.fixture
def cloud_ply(tmp_path):
    rng = np.random.default_rng(0)
    n = 400
    pts = np.c_[rng.uniform(-1, 1, n), rng.uniform(-0.2, 0.2, n), rng.uniform(2, 4, n)]
    c = PointCloud(pts, {"counts": rng.integers(1, 50, n).astype(np.int32),
                         "pixel": rng.integers(0, 192, n).astype(np.int32),
                         "range": np.linalg.norm(pts, axis=1),
                         "sigma_r": rng.uniform(1e-3, 1e-2, n),
                         "sigma_phi": rng.uniform(1e-4, 1e-3, n)})
    return write_cloud(tmp_path / "c.ply", c), c


def test_export_chain(tmp_path, cloud_ply, capsys):
    src, ref = cloud_ply
    assert main(["export", str(src), "-o", str(tmp_path / "c.las")]) == 0
    assert main(["-q", "export", str(tmp_path / "c.las"), "-o", str(tmp_path / "c.pcd")]) == 0
    out = capsys.readouterr().out
    assert "c.las: 400 points" in out and "c.pcd" not in out  # second one was quiet
    got = read_cloud(tmp_path / "c.pcd")
    assert np.abs(got.points - ref.points).max() <= LAS_SCALE / 2 * (1 + 1e-9)
    for k, v in ref.attributes.items():
        np.testing.assert_array_equal(got[k], v)


def test_export_bad_input(tmp_path, cloud_ply, capsys):
    src, _ = cloud_ply
    assert main(["export", str(tmp_path / "none.ply"), "-o", str(tmp_path / "x.las")]) == 2
    assert main(["export", str(src), "-o", str(tmp_path / "x.obj")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2
    assert "file not found" in err[0] and "extension" in err[1]
    assert not (tmp_path / "x.obj").exists()


@pytest.mark.skipif(not render_available()[0], reason="headless OpenGL unavailable")
def test_render(tmp_path, cloud_ply, capsys):
    src, _ = cloud_ply
    out = tmp_path / "v.png"
    assert main(["render", str(src), "-o", str(out), "--color-by", "sigma_r",
                 "--width", "200", "--height", "150", "--view", "top"]) == 0
    img = cv2.imread(str(out))
    assert img.shape == (150, 200, 3) and (img != 255).any()
    assert "400 points" in capsys.readouterr().out


def test_render_bad_input(tmp_path, cloud_ply, capsys):
    src, _ = cloud_ply
    assert main(["render", str(src), "-o", str(tmp_path / "v.png"), "--color-by", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["render", str(src), "-o", str(tmp_path / "v.png"), "--view", "under"])
    assert e.value.code == 2


def test_view_without_display(cloud_ply, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(cloud_ply[0])]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no display" in err


def test_plot_commands(tmp_path, cloud_ply, capsys):
    rng = np.random.default_rng(1)
    sig = np.zeros((1, 16, 300), np.int32)
    sig[..., 50] = 3
    noise = rng.poisson(0.2, sig.shape)
    h = write_histograms(tmp_path / "h.h5", sig + noise, sig, noise, {"source": "test"})
    assert main(["plot", "histograms", str(h), "-o", str(tmp_path / "h.png"),
                 "--max-code", "256"]) == 0
    assert main(["plot", "cloud", str(cloud_ply[0]), "-o", str(tmp_path / "t.png")]) == 0
    assert main(["plot", "acquisition", "--shots", "200", "-o", str(tmp_path / "a.png")]) == 0
    out = capsys.readouterr().out
    assert f"signal {int(sig.sum())}" in out and "mean accumulations" in out
    for name in ("h.png", "t.png", "a.png"):
        assert cv2.imread(str(tmp_path / name)) is not None
    assert main(["plot", "-q", "cloud", str(cloud_ply[0]), "-o", str(tmp_path / "q.png")]) == 0
    assert capsys.readouterr().out == ""


def test_plot_bad_input(tmp_path, cloud_ply, capsys):
    assert main(["plot", "histograms", str(cloud_ply[0]), "-o", str(tmp_path / "h.png")]) == 2
    assert main(["plot", "cloud", str(cloud_ply[0]), "-o", str(tmp_path / "t.gif")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "HDF5" in err[0] and ".gif" in err[1]


@pytest.mark.parametrize("cmd", ["export", "view", "render", "plot"])
def test_help_has_example(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "example" in out and f"\n  mems-stereo {cmd} " in out
