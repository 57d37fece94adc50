"""Regenerate the two-axis sample recordings of samples/ bit for bit from their seeds.

    python samples/make_samples_2d.py              # both, into samples/
    python samples/make_samples_2d.py --only lissajous64
    python samples/make_samples_2d.py --out /tmp/s

Made by :func:`mems_stereo.sim.simulate2d.simulate_2d` with
``numpy.random.default_rng(seed)``, the presets ``lissajous64`` and
``raster128x96`` (written as ``<name>_system.json``) and the scene
``twoaxis_scene.json`` (walls, floor, boxes, cylinders), at 100 kHz background.
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
from mems_stereo.model.scanner2d import TWO_AXIS_PRESETS
from mems_stereo.model.system import save_system
from mems_stereo.sim.scene import load_scene
from mems_stereo.sim.simulate2d import simulate_2d

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Sample2D:
    name: str  # preset and output stem
    seed: int
    n_shots: int
    background_hz: float = 1e5


SAMPLES_2D = [
    Sample2D("lissajous64", 21, 60000),
    Sample2D("raster128x96", 22, 100000),
]


def make(sample: Sample2D, out: Path) -> Path:
    system = TWO_AXIS_PRESETS[sample.name]()
    save_system(system, out / f"{sample.name}_system.json")
    rec = simulate_2d(system, load_scene(HERE / "twoaxis_scene.json"), sample.n_shots,
                      rng=np.random.default_rng(sample.seed),
                      background_hz=sample.background_hz, truth_per_shot=False)
    return write_recording_2d(out / f"{sample.name}.h5", rec)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE))
    ap.add_argument("--only", choices=[s.name for s in SAMPLES_2D], default=None)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for s in SAMPLES_2D:
        if args.only and s.name != args.only:
            continue
        p = make(s, out)
        print(f"{p}: {p.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
