"""Calibrate the bundled calibration samples; print the time, the estimates and the wall check.

    OMP_NUM_THREADS=1 python benchmarks/bench_calibrate.py

Prints, for the three recordings samples/calib_*m.h5 (start: the nominal
system of the recordings; truth: samples/calib_true_system.json):

1. the wall-clock time of :func:`calib.calibrate_system` without and with the
   measured target distances of samples/calib_distances.json;
2. each estimate with its σ and its error against the truth (in σ), for both
   runs, and the correlations that the distances break;
3. the wall check: each recording processed by the package's pipeline
   (:func:`mems_stereo.pipeline.run.process_recording`, one fused point per
   histogram peak) with the nominal, both calibrated and the true system;
   the median |distance| of the points to the true wall plane
   (samples/calib_<d>m_scene.json) and the ratio nominal / calibrated.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mems_stereo.calib.calibrate import calibrate_system, read_target_distances
from mems_stereo.calib.model import PARAM_UNIT

from mems_stereo.io.recording import read_recording
from mems_stereo.model.system import load_system
from mems_stereo.pipeline.run import process_recording

SAMPLES = ROOT / "samples"


def wall_plane(scene_path):
    """(unit normal (3,), point on the plane (3,)) of the scene's first object, camera frame, m."""
    obj = json.loads(Path(scene_path).read_text())["objects"][0]
    n = np.asarray(obj["normal"], float)
    return n / np.linalg.norm(n), np.asarray(obj["center"], float)


def wall_median_distance(path, system, scene_path) -> tuple[float, int]:
    """Median |distance| (m) of the points processed from ``path`` to the wall; point count."""
    n, c = wall_plane(scene_path)
    pts = process_recording(path, system=system).cloud.points
    return float(np.median(np.abs((pts - c) @ n))), int(pts.shape[0])


def _calibrate(recs, **kw):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_system(recs, **kw)
    return res, time.perf_counter() - t0


def speed_case() -> None:
    """Issue 12's speed target: ``mems-stereo calibrate`` of four walls × 12,800 shots
    at 1 MHz background (simulated, written as HDF5), on one core."""
    import math
    import tempfile

    from mems_stereo.calib.family import Case, Wall, simulate_case

    from mems_stereo.cli import main as cli
    from mems_stereo.model.system import burkard2022
    from mems_stereo.sim import write_simulation

    nom = burkard2022()
    spec = [(1.0, 8, 0.5), (1.8, -10, 0.5), (2.8, 6, 0.5), (4.2, -5, 0.5)]
    case = Case([Wall(d, math.radians(y), 0.0, 0.5, f, 12800, 1e6) for d, y, f in spec],
                {"theta0": 4e-3, "baseline_x": 5e-3, "tdc_offset": 1e-9}, 77,
                [d for d, _, _ in spec])
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, r in enumerate(simulate_case(case, nom)):
            paths.append(str(write_simulation(Path(tmp) / f"wall{i}.h5", r)))
        for extra in ([], ["--target-distance", *map(str, case.measured)]):
            t0, c0 = time.perf_counter(), time.process_time()
            import contextlib
            import io

            with contextlib.redirect_stdout(io.StringIO()):
                rc = cli(["calibrate", *paths, "-o", str(Path(tmp) / "cal.json"), *extra])
            print(f"mems-stereo calibrate, 4 walls x 12,800 shots at 1 MHz"
                  f"{' with distances' if extra else ''}: exit {rc}, "
                  f"{time.perf_counter() - t0:.1f} s wall, "
                  f"{time.process_time() - c0:.1f} s CPU (OMP_NUM_THREADS="
                  f"{__import__('os').environ.get('OMP_NUM_THREADS', 'unset')})")


def main() -> int:
    paths = sorted(SAMPLES.glob("calib_*m.h5"), key=lambda p: float(p.stem[6:-1]))
    if not paths:
        print("no samples/calib_*m.h5 found")
        return 1
    recs = [read_recording(p, truth=False) for p in paths]
    true = load_system(SAMPLES / "calib_true_system.json")
    dists, stds, kind = read_target_distances(SAMPLES / "calib_distances.json", paths)
    n_shots = sum(r.n_shots for r in recs)
    free, dt_free = _calibrate(recs, on_unobservable="warn")
    known, dt_known = _calibrate(recs, target_distances=dists, distance_std=stds,
                                 distance_kind=kind)
    print(f"calibrate_system on {len(paths)} recordings ({n_shots} shots): "
          f"{dt_free:.1f} s without distances, {dt_known:.1f} s with")
    speed_case()
    print()
    print("with the measured distances (" + ", ".join(f"{d:.3f}" for d in dists)
          + f" m along the optical axis, σ {stds[0] * 1e3:.1f} mm):")
    print(known.report)
    print()
    print("| parameter | nominal | without distances | error/σ | with distances | error/σ "
          "| true |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for nm in known.names:
        f, unit = PARAM_UNIT[nm]
        tv = true.get_param(nm)
        cells = []
        for r in (free, known):
            cells.append(f"{r.values[nm] * f:.4f} ± {r.std[nm] * f:.4f}")
            cells.append(f"{(r.values[nm] - tv) / r.std[nm]:+.2f}")
        print(f"| {nm} ({unit}) | {known.initial[nm] * f:.4f} | " + " | ".join(cells)
              + f" | {tv * f:.4f} |")
    print()
    print(f"θ0 error: {abs(free.values['theta0'] - true.get_param('theta0')) * 1e3:.3f} mrad "
          f"without, {abs(known.values['theta0'] - true.get_param('theta0')) * 1e3:.3f} mrad "
          "with distances")
    print("|correlation| > 0.9 without distances: "
          + ", ".join(f"{a}/{b} {c:+.3f}" for a, b, c in free.tradeoffs))
    print("|correlation| > 0.9 with distances:    "
          + ", ".join(f"{a}/{b} {c:+.3f}" for a, b, c in known.tradeoffs))
    ze = np.array(known.extra["axis_distance"])
    print("fitted optical-axis distances: " + ", ".join(
        f"{z:.4f} ± {s * 1e3:.2f} mm" for z, s in zip(ze, known.extra["axis_distance_std"])))
    print()
    print("Points on the walls: process_recording(path, system=...).cloud.points, median "
          "|distance| to the true wall plane")
    print("| wall | points | nominal | calibrated, no distances | ratio | calibrated, distances "
          "| ratio | true system |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    t0 = time.perf_counter()
    for p in paths:
        scene = p.with_name(p.stem + "_scene.json")
        a, na = wall_median_distance(p, None, scene)
        b, _ = wall_median_distance(p, free.system, scene)
        c, nc = wall_median_distance(p, known.system, scene)
        t, _ = wall_median_distance(p, true, scene)
        print(f"| {p.stem[6:]} | {na}/{nc} | {a * 1e3:.1f} mm | {b * 1e3:.1f} mm | {a / b:.1f}x | "
              f"{c * 1e3:.1f} mm | {a / c:.1f}x | {t * 1e3:.1f} mm |")
    print(f"(processing: {time.perf_counter() - t0:.1f} s for {4 * len(paths)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
