"""Calibrate the bundled calibration samples; print the time, the estimates and the wall check.

    python benchmarks/bench_calibrate.py [--threads-note]

Prints: wall-clock time of :func:`calib.calibrate_system` on
samples/calib_*m.h5 (start: the nominal system of the recordings), each
estimate with its σ and its error against samples/calib_true_system.json
(in σ), and the median distance of the processed points (classified and
triangulated by mems_stereo.classify / mems_stereo.points with the nominal
and with the calibrated system) to each true wall plane.  Run with
OMP_NUM_THREADS=1 for the one-core figure.
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

from calib.calibrate import calibrate_system  # noqa: E402
from calib.model import PARAM_UNIT  # noqa: E402
from mems_stereo.classify import classify_bins  # noqa: E402
from mems_stereo.points import detection_points  # noqa: E402
from mems_stereo.recording import read_recording  # noqa: E402
from mems_stereo.scanner import scan_angles  # noqa: E402
from mems_stereo.system import load_system  # noqa: E402

SAMPLES = ROOT / "samples"


def wall_distances(rec, system, scene_path):
    """Median |distance| (m) of stereo and fused points of signal detections to the true wall."""
    obj = json.loads(Path(scene_path).read_text())["objects"][0]
    n = np.asarray(obj["normal"], float)
    n /= np.linalg.norm(n)
    c = np.asarray(obj["center"], float)
    theta, valid = scan_angles(rec.shot_time, rec.zero_crossings, rec.rising, system.scanner)
    labels = classify_bins(system, rec.bins, theta, valid)
    k, r, col = np.nonzero(labels == 1)
    pts = detection_points(system, k, r, col, rec.bins[k, r, col], np.nan_to_num(theta))
    out = {}
    ok = pts.ok
    for name in ("stereo", "fused"):
        d = (getattr(pts, name)[ok] - c) @ n
        # per pixel: the median distance of its detections (what a per-pixel peak gives)
        px = col[ok]
        med = [np.median(d[px == q]) for q in np.unique(px) if np.count_nonzero(px == q) >= 20]
        out[name] = float(np.median(np.abs(d)))
        out[name + "_pixel"] = float(np.median(np.abs(med)))
    return out


def main() -> int:
    paths = sorted(SAMPLES.glob("calib_*m.h5"), key=lambda p: float(p.stem[6:-1]))
    if not paths:
        print("no samples/calib_*m.h5 found")
        return 1
    recs = [read_recording(p) for p in paths]
    true = load_system(SAMPLES / "calib_true_system.json")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_system(recs)
    dt = time.perf_counter() - t0
    print(f"calibrate_system on {len(paths)} recordings "
          f"({sum(r.n_shots for r in recs)} shots): {dt:.1f} s")
    print(res.report)
    print()
    print("| parameter | nominal | estimate | σ | true | error/σ |")
    print("| --- | --- | --- | --- | --- | --- |")
    for nm in res.names:
        f, unit = PARAM_UNIT[nm]
        tv = true.get_param(nm)
        z = (res.values[nm] - tv) / res.std[nm]
        print(f"| {nm} ({unit}) | {res.initial[nm] * f:.4f} | {res.values[nm] * f:.4f} | "
              f"{res.std[nm] * f:.4f} | {tv * f:.4f} | {z:+.2f} |")
    print()
    print("| wall | points | nominal: median distance | calibrated | ratio |")
    print("| --- | --- | --- | --- | --- |")
    for p, rec in zip(paths, recs):
        scene = p.with_name(p.stem + "_scene.json")
        a = wall_distances(rec, rec.system, scene)
        b = wall_distances(rec, res.system, scene)
        for key, what in (("stereo", "stereo, per detection"), ("fused", "fused, per detection"),
                          ("stereo_pixel", "stereo, median per pixel"),
                          ("fused_pixel", "fused, median per pixel")):
            print(f"| {p.stem} | {what} | {a[key] * 1e3:.1f} mm | {b[key] * 1e3:.1f} mm | "
                  f"{a[key] / b[key]:.1f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
