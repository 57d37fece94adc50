"""Benchmark: each hardware imperfection alone, processed with the ideal and the full model.

    nice .venv/bin/python benchmarks/bench_hardware_model.py [--shots 4000] [--seed 1]

The room scene (``samples/room_scene.json``) under room light (1e5 Hz), recorded by
the samples' true geometry (``samples/make_samples.py``: nominal + CALIB_OFFSETS) with
ideal hardware, with one imperfection of ``Imperfections.typical()`` at a time, with
all of them and with a strong pulse tail (40 %, 8 ns); the imperfections' random
parts drawn with ``numpy.random.default_rng(5)``, the recordings with ``--seed``.
Each recording is processed with the exact geometry and the ideal hardware model,
and with the exact full model (``docs/hardware.md``).  Printed per row: median
|range − true range|, RMS of (range − true)/σ_r, the median signed error of the
time-of-flight estimate, RMS of the stereo/ToF normalised difference, points; and
the CPU.  The log goes to ``benchmarks/results/hardware_model.txt``.  About 5 min on
one core.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "samples"))

from make_samples import calib_true_system, nominal_system  # noqa: E402

from mems_stereo.pipeline.run import process_recording  # noqa: E402
from mems_stereo.sim import Imperfections, SimulationOptions, load_scene, simulate  # noqa: E402
from mems_stereo.sim.score import MAX_TRUE_RANGE, true_ranges  # noqa: E402

TYP = Imperfections.typical()
ROWS = [
    ("ideal hardware", Imperfections()),
    ("0.3 % third harmonic", Imperfections(TYP.harmonics)),
    ("edge delays 300 / 100 ns", Imperfections(rising_delay=300e-9, falling_delay=100e-9)),
    ("pulse tail 20 %, 2 ns", Imperfections(tail_fraction=0.2, tail_decay=2e-9)),
    ("pulse tail 40 %, 8 ns", Imperfections(tail_fraction=0.4, tail_decay=8e-9)),
    ("pixel offsets σ 100 ps", Imperfections(pixel_offset_sigma=100e-12)),
    ("DNL 0.1 periodic + 0.03 random", Imperfections(dnl_periodic=0.1, dnl_random=0.03)),
    ("all typical", TYP),
]


def figures(cloud, scene) -> dict:
    """The row's figures of one processed cloud against the scene."""
    rt = true_ranges(scene, cloud.points)
    ok = np.isfinite(rt) & (rt <= MAX_TRUE_RANGE)
    e = (cloud["range"] - rt)[ok]
    return {"median": float(np.median(np.abs(e))),
            "rms_pull": float(np.sqrt(np.mean((e / cloud["sigma_r"][ok]) ** 2))),
            "tof_bias": float(np.median((cloud["range_tof"] - rt)[ok])),
            "rms_z": float(np.sqrt(np.nanmean(cloud["stereo_tof_z"][ok] ** 2))),
            "points": int(ok.sum())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    scene = load_scene(ROOT / "samples" / "room_scene.json")
    base = calib_true_system()
    lines = [f"bench_hardware_model: room, {args.shots} shots, seed {args.seed}, "
             f"CPU {platform.processor() or platform.machine()}",
             "| recording | model | median error | RMS err/σ_r | ToF bias | RMS z | points |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    print("\n".join(lines), flush=True)
    t0 = time.time()
    for label, imp in ROWS:
        true = imp.apply(base, np.random.default_rng(5))
        rec = simulate(nominal_system(), scene, args.shots,
                       rng=np.random.default_rng(args.seed), true_system=true,
                       options=SimulationOptions(drift=1e-3))
        models = [("ideal", base)] + ([] if true.ideal_hardware else [("full", true)])
        for name, system in models:
            f = figures(process_recording(rec, system=system).cloud, scene)
            line = (f"| {label} | {name} | {f['median'] * 100:.2f} cm | {f['rms_pull']:.2f} | "
                    f"{f['tof_bias'] * 100:+.1f} cm | {f['rms_z']:.2f} | {f['points']} |")
            print(line, flush=True)
            lines.append(line)
    lines.append(f"wall time {time.time() - t0:.0f} s")
    print(lines[-1])
    out = ROOT / "benchmarks" / "results" / "hardware_model.txt"
    out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
