"""Regenerate the two-axis sample recordings of samples/ bit for bit from their seeds.

    python samples/make_samples_2d.py              # both, into samples/
    python samples/make_samples_2d.py --only lissajous64
    python samples/make_samples_2d.py --out /tmp/s

Made by :func:`mems_stereo.sim.simulate2d.simulate_2d` with
``numpy.random.default_rng(seed)``, the presets ``lissajous64`` and
``raster128x96`` (the nominal systems, written into the files and as
``<name>_system.json``) and the scene ``twoaxis_scene.json`` (walls, floor,
boxes, cylinders), at 100 kHz background; and three flat-wall calibration
recordings ``lissajous64_calib_<d>m.h5`` at reduced laser power
(``CALIB_PEAK_POWER``).

One story per scanner, as for the line sensor (samples/make_samples.py): the
Lissajous scanner's recordings, ``lissajous64.h5`` and its three walls, are
all made by one true system, ``lissajous64_calib_true_system.json`` (the
nominal preset off by the offsets in ``CALIB_OFFSETS``); the walls calibrate
it.  No walls ship for the raster scanner: ``raster128x96.h5`` is made by its
nominal preset (``Sample2D.true_system = "nominal"``).
Only the per-event truth labels are stored (the per-shot truth would triple
the files); ``benchmarks/bench_twoaxis.py`` scores them against the scene.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mems_stereo.io.recording2d import write_recording_2d
from mems_stereo.model.presets import TWO_AXIS_PRESETS
from mems_stereo.model.system import save_system
from mems_stereo.sim.scene import load_scene
from mems_stereo.sim.simulate2d import Simulation2DOptions, simulate_2d

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Sample2D:
    name: str  # preset and output stem
    seed: int
    n_shots: int
    true_system: str  # "calib" (nominal + CALIB_OFFSETS, the walls' system) or "nominal"
    background_hz: float = 1e5


SAMPLES_2D = [
    Sample2D("lissajous64", 21, 60000, "calib"),
    Sample2D("raster128x96", 22, 100000, "nominal"),
]


#: the Lissajous samples' true system (lissajous64.h5 and the calibration walls):
#: nominal lissajous64 + these (SI units)
CALIB_OFFSETS = {"theta0": +3e-3, "theta0_2": -2e-3, "theta_mech_max": +7.9e-4,
                 "theta_mech_max_2": -9.6e-4, "phase_offset": 0.01, "phase_offset_2": -0.015,
                 "baseline_x": +0.004, "baseline_y": +0.003, "baseline_z": +0.002,
                 "tdc_offset": 1e-9}
#: walls: (distance m, yaw α rad, pitch β rad, seed); plane n(α, β)·x = distance
CALIB_WALLS = [(1.5, 0.2, 0.1, 31), (2.5, -0.15, -0.12, 32), (4.0, 0.1, 0.15, 33)]
CALIB_SHOTS = 40000
CALIB_PEAK_POWER = 0.03  # W: μ <= 0.5 photons per shot on the walls (little pile-up)


def calib_true_system():
    """The true system of the Lissajous samples: the preset + ``CALIB_OFFSETS``."""
    from mems_stereo.calib.twoaxis import get_param_2d, with_params_2d

    nom = TWO_AXIS_PRESETS["lissajous64"]()
    return with_params_2d(nom, **{k: get_param_2d(nom, k) + v for k, v in CALIB_OFFSETS.items()})


def wall_scene(dist: float, alpha: float, beta: float):
    from mems_stereo.sim.scene import scene_from_dict

    n = np.array([np.sin(alpha) * np.cos(beta), np.sin(beta), np.cos(alpha) * np.cos(beta)])
    return scene_from_dict({"format": "mems-stereo/scene", "version": 1, "name": "wall",
                            "objects": [{"type": "plane", "center": (n * dist).tolist(),
                                         "normal": (-n).tolist(), "size": [20.0, 20.0],
                                         "reflectivity": 0.5}]})


def make_calib(out: Path) -> list[Path]:
    from dataclasses import replace

    from mems_stereo.sim.simulate2d import default_link

    nom = TWO_AXIS_PRESETS["lissajous64"]()
    true = calib_true_system()
    save_system(true, out / "lissajous64_calib_true_system.json")
    link = replace(default_link(), peak_power=CALIB_PEAK_POWER)
    paths = []
    for dist, a, b, seed in CALIB_WALLS:
        rec = simulate_2d(nom, wall_scene(dist, a, b), CALIB_SHOTS,
                          rng=np.random.default_rng(seed), true_system=true,
                          options=Simulation2DOptions(link=link, truth_per_shot=False))
        paths.append(write_recording_2d(out / f"lissajous64_calib_{dist:.1f}m.h5", rec))
    return paths


def make(sample: Sample2D, out: Path) -> Path:
    system = TWO_AXIS_PRESETS[sample.name]()
    save_system(system, out / f"{sample.name}_system.json")
    true = calib_true_system() if sample.true_system == "calib" else None
    rec = simulate_2d(system, load_scene(HERE / "twoaxis_scene.json"), sample.n_shots,
                      rng=np.random.default_rng(sample.seed),
                      background_hz=sample.background_hz, true_system=true,
                      options=Simulation2DOptions(truth_per_shot=False))
    return write_recording_2d(out / f"{sample.name}.h5", rec)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE))
    ap.add_argument("--only", choices=[s.name for s in SAMPLES_2D] + ["calib"], default=None)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for s in SAMPLES_2D:
        if args.only and s.name != args.only:
            continue
        p = make(s, out)
        print(f"{p}: {p.stat().st_size / 1e6:.2f} MB")
    if args.only in (None, "calib"):
        for p in make_calib(out):
            print(f"{p}: {p.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
