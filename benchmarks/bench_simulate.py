"""Benchmark: simulate one second of the paper's system (20,000 shots x 192 pixels).

    .venv/bin/python benchmarks/bench_simulate.py [--shots 20000] [--repeat 3] [--all-cores]

Pinned to one CPU core (``os.sched_setaffinity``) unless ``--all-cores``.
Prints the best wall time of the simulation (no file output), the real-time
factor (simulated seconds of laser shots / wall seconds; target >= 10), and
the time to write the recording (gzip'd HDF5) for reference.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mems_stereo.model.system import burkard2022
from mems_stereo.sim import load_scene, simulate, write_simulation


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--all-cores", action="store_true")
    args = ap.parse_args()
    if not args.all_cores and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    system = burkard2022()
    scene = load_scene(ROOT / "samples" / "room_scene.json")
    simulate(system, scene, 10, rng=np.random.default_rng(0))  # warm up (Open3D, BVH)
    real = args.shots / system.laser.f_rep
    w, h = system.receiver.image_size
    print(f"{args.shots} shots x {w * h} pixels = {real:g} s of laser shots, on {cores} core(s)")
    for label, bg in (("room light 100 kHz", 1e5), ("floodlight 6 MHz", 6e6)):
        best = np.inf
        for i in range(args.repeat):
            t0 = time.perf_counter()
            rec = simulate(system, scene, args.shots, rng=np.random.default_rng(i),
                           background_hz=bg)
            best = min(best, time.perf_counter() - t0)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_simulation(Path(tmp) / "bench.h5", rec)
            t_write = time.perf_counter() - t0
        n_det = int((rec.bins > 0).sum())
        print(f"  {label:20s} simulate {best:.3f} s  real-time factor {real / best:6.1f}x  "
              f"({n_det / args.shots:.1f} detections/shot; writing the .h5 {t_write:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
