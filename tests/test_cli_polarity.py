"""Inverted zero-crossing polarity: detected from the detections.

Families of simulated recordings (scenes × background × seeds, own seeds):
every control passes without a warning, every inverted copy with a usable
laser return is refused (or, at a high background, at least warned about),
and recordings of background alone (no information on the polarity) are
never refused: their z stays within the noise.
"""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from mems_stereo.cli import main
from mems_stereo.cli._crosscheck import REFUSE_Z, WARN_Z, polarity_evidence
from mems_stereo.model.system import resolve_system
from mems_stereo.sim.scene import load_scene
from mems_stereo.sim.simulate import simulate, write_simulation

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _invert(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f["scanner/rising"][...] = 1 - f["scanner/rising"][()]


def _simulated(d: Path, scene: str, bg: float, seed: int, signal: bool = True) -> Path:
    rec = simulate(resolve_system("burkard2022"), load_scene(SAMPLES / scene), 800,
                   rng=np.random.default_rng(1000 + seed), background_hz=bg)
    if not signal:  # background alone: the laser returns removed
        rec.bins[rec.truth["label"] == 1] = 0
    p = d / f"{Path(scene).stem}_{bg:.0e}_{seed}_{int(signal)}.h5"
    write_simulation(p, rec)
    return p


@pytest.mark.slow
def test_polarity_family(tmp_path):
    rows = []
    for scene in ("room_scene.json", "calib_1.5m_scene.json", "calib_4.0m_scene.json"):
        for bg in (1e5, 1e6):
            for seed in range(2):
                p = _simulated(tmp_path, scene, bg, seed)
                z0 = polarity_evidence(p).z
                _invert(p)
                z1 = polarity_evidence(p).z
                rows.append((scene, bg, seed, z0, z1))
                p.unlink()
    z0 = np.array([r[3] for r in rows])
    z1 = np.array([r[4] for r in rows])
    low = np.array([r[1] == 1e5 for r in rows])
    print(f"\ncontrols: z {z0.min():.1f}..{z0.max():.1f}, warned {np.mean(z0 >= WARN_Z):.0%}; "
          f"inverted: z {z1.min():.1f}..{z1.max():.1f}, refused {np.mean(z1 >= REFUSE_Z):.0%} "
          f"(background 1e5: {np.mean(z1[low] >= REFUSE_Z):.0%}), warned or refused "
          f"{np.mean(z1 >= WARN_Z):.0%}")
    assert np.all(z0 < WARN_Z), rows          # no control is warned about, let alone refused
    assert np.all(z1[low] >= REFUSE_Z), rows  # room light: every inversion refused
    assert np.all(z1 >= WARN_Z), rows         # 1e6 Hz: at least a warning


def test_background_alone_is_never_refused(tmp_path):
    """Without laser returns the data say nothing on the polarity: z ~ N(0, 1)."""
    zs = []
    for seed in range(4):
        p = _simulated(tmp_path, "room_scene.json", 1e6, seed, signal=False)
        zs += [polarity_evidence(p).z]
        _invert(p)
        zs += [polarity_evidence(p).z]
        p.unlink()
    zs = np.array(zs)
    print(f"\nbackground alone: z mean {zs.mean():.2f}, sd {zs.std():.2f}, max |z| "
          f"{np.abs(zs).max():.2f}")
    assert np.all(np.abs(zs) < WARN_Z), zs


def _cli(argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(argv)
    return rc, err.getvalue()


@pytest.mark.parametrize("cmd", ["process", "calibrate"])
def test_cli_refuses_inverted_polarity(cmd, tmp_path):
    src = "room.h5" if cmd == "process" else "calib_2.5m.h5"
    shutil.copy(SAMPLES / src, tmp_path / "inv.h5")
    _invert(tmp_path / "inv.h5")
    argv = ([cmd, str(tmp_path / "inv.h5"), "-o", str(tmp_path / "o.ply")] if cmd == "process"
            else [cmd, str(SAMPLES / "calib_1.5m.h5"), str(tmp_path / "inv.h5"), "-o",
                  str(tmp_path / "c.json")])
    rc, err = _cli(argv)
    lines = err.strip().splitlines()  # one line (an indented advice line may follow)
    assert rc == 2 and (len(lines) == 1 or lines[1].startswith("  ")), err
    assert "inv.h5: /scanner/rising" in err and "polarity looks inverted" in err, err
    assert sorted(x.name for x in tmp_path.iterdir()) == ["inv.h5"]
    # the control: the same recording as recorded is processed, nothing said on polarity
    if cmd == "process":
        rc, err = _cli([cmd, str(SAMPLES / src), "-o", str(tmp_path / "o.ply")])
        assert rc == 0 and "polarity" not in err, err
