"""Two-axis scanner + 2-D SPAD array: recall, point error and coverage (issue 17).

Prints
  * for each given recording (default: samples/lissajous64.h5 and, if present,
    samples/raster128x96.h5, scored against samples/twoaxis_scene.json; processed
    with ``<stem>_calib_true_system.json`` beside it when there is one, the system
    that recorded it, else with its own nominal ``/system``):
    signal recall of the classification, median point error of the points
    whose true surface lies within 6 m, and the coverage of lit pixels;
  * over random cases from the family the issue names (rooms of walls, floor,
    boxes and cylinders at random places, sizes and reflectivities; random
    mirror phases; 100 kHz background), drawn with their own seeds: the same
    figures as distributions, the share of laser returns the gate lost, and the
    pulls of the range error against the propagated σ_r.

Definitions
  recall     : laser-return detections (truth label 1) classified signal / all of them.
  point error: |x̂ − x_true|, x_true the true surface point on the pixel's centre
               ray (the pixel's point is the pixel ray ∩ path-length ellipsoid).
  lit pixel  : a pixel with >= 3 laser-return detections recorded (the fewest a
               peak may have); coverage = lit pixels with a point / lit pixels.
               (Also printed for >= 1 return.)

Run:  .venv/bin/python benchmarks/bench_twoaxis.py [--cases 8] [--shots 40000]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

from mems_stereo.io.recording2d import read_recording_2d  # noqa: E402
from mems_stereo.model.camera import pixels_to_rays  # noqa: E402
from mems_stereo.model.presets import lissajous64  # noqa: E402
from mems_stereo.model.system import load_system  # noqa: E402
from mems_stereo.pipeline.twoaxis import process_recording_2d  # noqa: E402
from mems_stereo.sim.scene import load_scene, scene_from_dict  # noqa: E402
from mems_stereo.sim.simulate2d import simulate_2d  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def score(rec, scene, result=None, within: float = 6.0) -> dict:
    """Recall, point errors within ``within`` m, coverage of lit pixels, pulls."""
    res = process_recording_2d(rec) if result is None else result
    s = rec.system
    w, h = s.receiver.image_size
    lab = np.asarray(rec.truth["label"])
    true_sig = np.bincount(rec.event_pixel[lab == 1], minlength=w * h)
    c = res.cloud
    pix = c["row"].astype(np.int64) * w + c["pixel"]
    uv = np.stack([c["pixel"], c["row"]], 1).astype(float)
    hits = scene.cast(np.zeros(3), pixels_to_rays(uv, s.receiver.camera_matrix,
                                                  s.receiver.dist_coeffs))
    rng_true = np.linalg.norm(hits.point, axis=1)
    near = np.isfinite(rng_true) & (rng_true <= within)
    err = np.linalg.norm(c.points - hits.point, axis=1)
    pull = (np.linalg.norm(c.points, axis=1) - rng_true) / c["sigma_r"]
    has_pt = np.zeros(w * h, bool)
    has_pt[pix] = True
    lit3, lit1 = true_sig >= 3, true_sig >= 1
    return {
        "recall": res.truth["recall"],
        "noise_rejection": res.truth["noise_rejection"],
        "median_err": float(np.median(err[near])) if near.any() else float("nan"),
        "p90_err": float(np.percentile(err[near], 90)) if near.any() else float("nan"),
        "n_near": int(near.sum()),
        "coverage3": float(has_pt[lit3].mean()) if lit3.any() else float("nan"),
        "coverage1": float(has_pt[lit1].mean()) if lit1.any() else float("nan"),
        "n_lit3": int(lit3.sum()),
        "points": len(c),
        "read_fraction": res.counts["read_fraction"],
        "pull_median_abs": float(np.median(np.abs(pull[near]))) if near.any() else np.nan,
        "gate_lost": (float(rec.truth["signal_lost"]) / max(1, int(rec.truth["signal_total"])))
        if "signal_lost" in rec.truth else float("nan"),
    }


def random_room(rng: np.random.Generator) -> dict:
    """A room of the issue's family: back wall, side wall, floor, 1-3 boxes, 1-2 cylinders."""
    zb = rng.uniform(3.5, 7.5)
    objs = [
        {"type": "plane", "center": [rng.uniform(-0.5, 0.5), 0.0, zb], "normal": [0, 0, -1],
         "size": [8.0, 5.0], "reflectivity": rng.uniform(0.3, 0.9)},
        {"type": "plane", "center": [rng.choice([-1, 1]) * rng.uniform(0.8, 1.5), 0.0, zb / 2],
         "normal": [1, 0, 0], "size": [zb, 5.0], "reflectivity": rng.uniform(0.3, 0.9)},
        {"type": "plane", "center": [0.0, rng.uniform(0.6, 1.2), zb / 2], "normal": [0, -1, 0],
         "size": [8.0, zb], "reflectivity": rng.uniform(0.2, 0.6)},
    ]
    if objs[1]["center"][0] > 0:
        objs[1]["normal"] = [-1, 0, 0]
    for _ in range(rng.integers(1, 4)):
        z = rng.uniform(1.2, zb - 0.5)
        objs.append({"type": "box", "center": [rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.2, 0.4),
                                               z],
                     "size": list(rng.uniform(0.2, 0.8, 3)),
                     "rotation_deg": [0.0, float(rng.uniform(-40, 40)), 0.0],
                     "reflectivity": rng.uniform(0.2, 0.9)})
    for _ in range(rng.integers(1, 3)):
        z = rng.uniform(1.2, zb - 0.5)
        objs.append({"type": "cylinder", "center": [rng.uniform(-0.3, 0.3) * z, 0.0, z],
                     "radius": rng.uniform(0.08, 0.3), "height": rng.uniform(0.5, 2.0),
                     "axis": [0, 1, 0], "reflectivity": rng.uniform(0.2, 0.9)})
    return {"format": "mems-stereo/scene", "version": 1, "name": "random room",
            "objects": objs}


def _line(name, s):
    print(f"{name:28s} recall {s['recall']:.4f}  noise rej. {s['noise_rejection']:.4f}  "
          f"median err (<=6 m) {100 * s['median_err']:.2f} cm (p90 {100 * s['p90_err']:.2f} cm, "
          f"{s['n_near']} pts)  coverage lit>=3 {s['coverage3']:.3f} (lit>=1 "
          f"{s['coverage1']:.3f}, {s['n_lit3']} px)  read {100 * s['read_fraction']:.2f} %  "
          f"|pull| median {s['pull_median_abs']:.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="*")
    ap.add_argument("--cases", type=int, default=8, help="random cases (default 8)")
    ap.add_argument("--shots", type=int, default=40000, help="shots per random case")
    ap.add_argument("--seed", type=int, default=1701)
    args = ap.parse_args(argv)
    recs = [Path(r) for r in args.recordings] or [
        p for p in (ROOT / "samples" / "lissajous64.h5", ROOT / "samples" / "raster128x96.h5")
        if p.exists()]
    scene = load_scene(ROOT / "samples" / "twoaxis_scene.json")
    print("== samples (100 kHz background), targets: recall >= 0.98, median err <= 2 cm "
          "within 6 m, coverage >= 0.8")
    for p in recs:
        rec = read_recording_2d(p)
        true_file = p.with_name(f"{p.stem}_calib_true_system.json")
        if true_file.exists():  # recorded by a true system that differs from the nominal one
            res = process_recording_2d(rec, system=load_system(true_file))
            _line(p.name, score(rec, scene, res))
            print(f"{'':28s} (processed with {true_file.name}, the system that recorded it)")
        else:
            _line(p.name, score(rec, scene))
    if args.cases <= 0:
        return 0
    print(f"== {args.cases} random rooms, lissajous64, {args.shots} shots, 100 kHz background, "
          f"seed {args.seed}")
    ss = np.random.SeedSequence(args.seed)
    rows = []
    for i, child in enumerate(ss.spawn(args.cases)):
        rng = np.random.default_rng(child)
        scene_i = scene_from_dict(random_room(rng))
        rec = simulate_2d(lissajous64(), scene_i, args.shots, rng=rng, background_hz=1e5)
        s = score(rec, scene_i)
        rows.append(s)
        _line(f"case {i}", s)
        print(f"{'':28s} gate lost {100 * s['gate_lost']:.3f} % of the laser returns")
    for k, fmt in (("recall", "{:.4f}"), ("median_err", "{:.4f} m"), ("coverage3", "{:.3f}"),
                   ("gate_lost", "{:.5f}"), ("pull_median_abs", "{:.2f}")):
        v = np.array([r[k] for r in rows])
        print(f"summary {k:16s} min " + fmt.format(v.min()) + "  median "
              + fmt.format(np.median(v)) + "  max " + fmt.format(v.max()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
