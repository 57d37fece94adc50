"""Epipolar readout gating on 2-D SPAD arrays: returns kept, pixels read, throughput (issue 17).

Random cases, each with its own seed: a two-axis system (Lissajous 64 x 64 or
raster 128 x 96; baseline x in [6, 20] cm, y and z within ±2 cm; focal length
4.5-8 mm), a true system off the nominal one by calibration-sized errors
(rest angles ±0.3 mrad, baseline ±2 mm per axis), a random room of walls,
floor, boxes and cylinders (benchmarks/bench_twoaxis.py) and 100 kHz
background.  The gate (working range 0.5-8 m, half width from the spot model)
is computed from the *nominal* system and the monitors' angles, as hardware
would.  Printed per case and as a summary:

  kept  : laser-return detections inside the gate / all laser-return detections
          on the array (target >= 99 %);
  read  : mean share of the array's pixels read per shot (target <= 5 %);
  and, on one case, the processing throughput with and without the gate: the
  pipeline (classification, per-pixel histograms, peaks, cloud) on a full
  readout of every pixel versus the gated readout of the same shots, as shots/s
  and pixel-slots/s (slots covered: shots x pixels of the array).

Run:  .venv/bin/python benchmarks/bench_gating.py [--cases 12] [--shots 20000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_twoaxis import random_room  # noqa: E402

from mems_stereo.model.presets import lissajous64, raster128x96  # noqa: E402
from mems_stereo.pipeline.twoaxis import process_recording_2d  # noqa: E402
from mems_stereo.sim.scene import scene_from_dict  # noqa: E402
from mems_stereo.sim.simulate2d import (  # noqa: E402
    Simulation2DOptions,
    default_gate_spec,
    simulate_2d,
)


def random_system(rng: np.random.Generator):
    s = lissajous64() if rng.random() < 0.6 else raster128x96()
    rc = s.receiver
    f = rng.uniform(4.5e-3, 8e-3)
    K = rc.camera_matrix.copy()
    K[0, 0] = K[1, 1] = f / rc.pixel_pitch[0]
    pos = np.array([-rng.uniform(0.06, 0.20), rng.uniform(-0.02, 0.02),
                    rng.uniform(-0.02, 0.02)])
    nominal = s.replace(receiver=replace(rc, camera_matrix=K),
                        scanner=replace(s.scanner, position=pos))
    sc = nominal.scanner
    true = nominal.replace(scanner=replace(
        sc, position=pos + rng.uniform(-2e-3, 2e-3, 3),
        theta0=sc.theta0 + rng.uniform(-3e-4, 3e-4),
        axis2=replace(sc.axis2, theta0=sc.axis2.theta0 + rng.uniform(-3e-4, 3e-4))))
    return nominal, true


def throughput(args, background_hz: float) -> None:
    """The same shots processed from a full readout and from the gated one."""
    rng = np.random.default_rng(args.seed + 1)
    s = lissajous64()
    scene = scene_from_dict(random_room(rng))
    n = args.throughput_shots
    kw = {"options": Simulation2DOptions(phase=0.3, phase2=1.7), "background_hz": background_hz}
    full = simulate_2d(s, scene, n, rng=np.random.default_rng(1), gate=None, **kw)
    gated = simulate_2d(s, scene, n, rng=np.random.default_rng(1), **kw)
    npix = s.receiver.image_size[0] * s.receiver.image_size[1]
    print(f"== throughput at {background_hz:.0e} Hz background, lissajous64")
    out = {}
    for name, rec in (("full readout", full), ("gated", gated)):
        process_recording_2d(rec)  # warm-up (numba compilation)
        t0 = time.perf_counter()
        res = process_recording_2d(rec)
        dt = time.perf_counter() - t0
        ev = res.timings["classify"] + res.timings["peaks+cloud"]
        out[name] = (dt, ev)
        print(f"throughput {name:12s}: {n} shots x {npix} px, {rec.n_events} events; whole "
              f"pipeline {dt:.2f} s -> {n / dt:,.0f} shots/s = {n * npix / dt:,.0f} "
              f"pixel-slots/s covered; classification + histograms + peaks {ev:.2f} s -> "
              f"{n * npix / ev:,.0f} pixel-slots/s covered ({res.counts['slots_read'] / ev:,.0f}"
              f" read slots/s), gate {res.timings['gate']:.2f} s; {len(res.cloud)} points, "
              f"recall {res.truth['recall']:.4f}")
    (tf, ef), (tg, eg) = out["full readout"], out["gated"]
    print(f"summary throughput: with the gate {100 * gated.read_count.mean() / npix:.2f} % of "
          f"the slots are read; the whole pipeline runs {tf / tg:.1f}x faster, the per-event "
          f"stages {ef / eg:.1f}x ({n * npix / eg:,.0f} vs {n * npix / ef:,.0f} pixel-slots/s)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=12)
    ap.add_argument("--shots", type=int, default=20000)
    ap.add_argument("--throughput-shots", type=int, default=20000)
    ap.add_argument("--throughput-backgrounds", type=float, nargs="*", default=[1e5, 1e6],
                    help="backgrounds (Hz) of the throughput comparison (default 1e5 1e6)")
    ap.add_argument("--seed", type=int, default=4242)
    args = ap.parse_args(argv)
    print(f"== {args.cases} random systems and rooms, {args.shots} shots each, 100 kHz "
          f"background, working range 0.5-8 m, seed {args.seed}")
    kept, read = [], []
    for i, child in enumerate(np.random.SeedSequence(args.seed).spawn(args.cases)):
        rng = np.random.default_rng(child)
        nominal, true = random_system(rng)
        scene = scene_from_dict(random_room(rng))
        spec = default_gate_spec(nominal)
        rec = simulate_2d(nominal, scene, args.shots, rng=rng, true_system=true, gate=spec,
                          options=Simulation2DOptions(truth_per_shot=False))
        tot, lost = int(rec.truth["signal_total"]), int(rec.truth["signal_lost"])
        w, h = nominal.receiver.image_size
        k = 1.0 - lost / max(1, tot)
        r = rec.read_count.mean() / (w * h)
        kept.append(k)
        read.append(r)
        print(f"case {i:2d}: {w:3d} x {h:2d} {nominal.scanner.axis2.mode:11s} baseline "
              f"{np.round(nominal.scanner.position * 100, 1)} cm, f = "
              f"{1e3 * nominal.receiver.camera_matrix[0, 0] * nominal.receiver.pixel_pitch[0]:.1f}"
              f" mm, half width {spec.half_width:.2f} px: kept {100 * k:.3f} % of {tot} "
              f"returns, read {100 * r:.2f} % of the pixels per shot "
              f"({rec.read_count.mean():.0f} px)")
    kept, read = np.array(kept), np.array(read)
    if kept.size:
        print(f"summary kept: min {100 * kept.min():.3f} %  median {100 * np.median(kept):.3f} % "
              f"(target >= 99 %)")
        print(f"summary read: max {100 * read.max():.2f} %  median {100 * np.median(read):.2f}"
              f" %  (target <= 5 %)")

    # throughput: the same shots processed with and without the gate
    for bg in args.throughput_backgrounds:
        throughput(args, bg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
