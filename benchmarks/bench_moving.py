"""Benchmark: frames of a moving scene (docs/frames.md), several seeds.

    nice .venv/bin/python benchmarks/bench_moving.py [--seeds 6] [--seconds 2] [--rate 10]
        [--log benchmarks/results/bench_moving.txt]

Scene (independent of the tests): a back wall at 6 m and a static cylinder at 3.5 m
(room light, 100 kHz + 1 kHz dark), a box 0.4 m wide at 2–2.5 m crossing the field of
view at 0.8 m/s (its start and depth vary with the seed) and a second box turning at
1 rad/s about its vertical axis.  The recording is simulated (the paper's system,
20 kHz shots), then processed (a) as frames of 1/rate s with the temporal fusion
(:func:`mems_stereo.iter_frames`) and (b) as one cloud.  Every frame point is scored
against the scene at its own time t (:func:`mems_stereo.sim.score.frame_scores`):

* moving: median |error| of the points on a moving object (target ≤ 3 cm);
* static after 1 s: median |error| of the frames' points on the static wall and cylinder
  in the frames that start at ≥ 1 s, in pixels the moving objects never cross, over the
  same of the whole recording processed as one cloud (target ≤ 1.5);
* false points per frame (farther than max(3σ_r, 10 cm) from every surface; target
  ≤ 1 %), RMS of error/σ_r over all frame points (target 0.7–1.4), and the coverage of
  each frame's lit pixels (target ≥ 0.9);
* the false-restart rate of the temporal fusion on the static pixels (a static pixel's
  point that does not agree with its own history).

Prints the figures per seed and over all seeds, the CPU model, and writes the log.
"""

from __future__ import annotations

import argparse
import io
import platform
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _machine import cpu_model  # noqa: E402

import mems_stereo as ms  # noqa: E402
from mems_stereo.pipeline.frames import iter_frames  # noqa: E402
from mems_stereo.pipeline.run import process_recording  # noqa: E402
from mems_stereo.sim import scene_from_dict, simulate  # noqa: E402
from mems_stereo.sim.motion import as_moving, motion_of  # noqa: E402
from mems_stereo.sim.score import frame_scores  # noqa: E402

BACKGROUND_HZ = 1e5
#: the processing's fewest detections for a peak (Settings.min_counts)
MIN_COUNTS = ms.Settings().min_counts


def scene_of(seed: int):
    """The benchmark's scene for a seed: start and depth of the crossing box vary."""
    r = np.random.default_rng(1000 + seed)
    z_box = float(r.uniform(2.0, 2.5))
    x0 = float(r.uniform(-1.3, -1.0))
    return as_moving(scene_from_dict({"name": f"moving box, seed {seed}", "objects": [
        {"type": "plane", "name": "wall", "center": [0, 0, 6], "normal": [0, 0, -1],
         "size": [14, 4], "reflectivity": 0.7},
        {"type": "cylinder", "name": "pillar", "center": [1.2, 0, 3.5], "radius": 0.2,
         "height": 2.0, "reflectivity": 0.6},
        {"type": "box", "name": "crossing box", "center": [x0, 0, z_box],
         "size": [0.4, 1.0, 0.4], "reflectivity": 0.5, "velocity": [0.8, 0, 0]},
        {"type": "box", "name": "turning box", "center": [0.35, 0, 4.2],
         "size": [0.5, 1.0, 0.3], "reflectivity": 0.6, "angular_rate": [0, 1.0, 0]}]}))


def moving_pixels(rec, scene) -> np.ndarray:
    """(H, W) bool: pixels within 3 columns of a moving object's true hit in any shot."""
    moving = [i for i, o in enumerate(scene.objects) if motion_of(o) is not None]
    pts = rec.truth["point"][np.isin(rec.truth["object"], moving)]
    rc = rec.system.receiver
    w, h = rc.image_size
    out = np.zeros((h, w), bool)
    if len(pts):
        uv = ms.project_points(pts, rc.camera_matrix, rc.dist_coeffs)
        cols = np.unique(np.rint(uv[:, 0]).astype(int))
        for dc in range(-3, 4):
            c = np.clip(cols + dc, 0, w - 1)
            out[:, c] = True
    return out


def run_seed(seed: int, seconds: float, rate: float) -> dict:
    scene = scene_of(seed)
    system = ms.preset("burkard2022")
    n = int(round(seconds * system.laser.f_rep))
    t0 = time.perf_counter()
    rec = simulate(system, scene, n, rng=np.random.default_rng(seed), background_hz=BACKGROUND_HZ)
    t_sim = time.perf_counter() - t0
    moving_ids = [i for i, o in enumerate(scene.objects) if motion_of(o) is not None]
    touched = moving_pixels(rec, scene)
    lab = rec.truth["label"]
    rows = []
    t0 = time.perf_counter()
    restart = np.zeros(0, bool)
    for f in iter_frames(rec, frame_rate=rate):
        inside = (rec.shot_time >= f.start) & (rec.shot_time < f.end)
        returns = np.sum(lab[inside] == 1, axis=0)
        s = frame_scores(f.cloud, scene, returns > 0)
        s["lit_min_counts"] = returns >= MIN_COUNTS
        s["lit_mask"] = returns > 0
        c = f.cloud
        static = ~np.isin(s["object"], moving_ids) & (s["object"] >= 0)
        quiet = static & ~touched[c["row"], c["pixel"]]
        rows.append({"frame": f, "s": s, "moving": ~static & (s["object"] >= 0),
                     "quiet": quiet})
        restart = np.concatenate([restart, (c["age"] == 1)[quiet]]) if f.index else restart
    t_frames = time.perf_counter() - t0
    whole = process_recording(rec)
    ws = frame_scores(_with_mid_time(whole.cloud, rec), scene, np.any(lab == 1, axis=0))
    wc = whole.cloud
    w_static = ~np.isin(ws["object"], moving_ids) & (ws["object"] >= 0)
    w_quiet = w_static & ~touched[wc["row"], wc["pixel"]]
    return {"seed": seed, "rows": rows, "whole_quiet": np.abs(ws["error"][w_quiet]),
            "t_sim": t_sim, "t_frames": t_frames, "restart": restart, "rate": rate}


def _with_mid_time(cloud, rec):
    """The whole recording's cloud with t = the recording's middle (static parts only are
    compared; their truth does not depend on t)."""
    cloud.attributes["t"] = np.full(len(cloud), 0.5 * (rec.shot_time[0] + rec.shot_time[-1]))
    return cloud


def figures(r: dict) -> dict:
    rows = r["rows"]
    err = np.concatenate([x["s"]["error"] for x in rows])
    sig = np.concatenate([x["s"]["sigma"] for x in rows])
    mov = np.concatenate([np.abs(x["s"]["error"][x["moving"]]) for x in rows])
    late = [x for x in rows if x["frame"].start - rows[0]["frame"].start >= 1.0 - 1e-9]
    quiet_late = np.concatenate([np.abs(x["s"]["error"][x["quiet"]]) for x in late]) \
        if late else np.zeros(0)
    fin = np.isfinite(err) & (sig > 0)
    false_frac = [x["s"]["false"].mean() if len(x["s"]["false"]) else 0.0 for x in rows]
    return {"moving_median": float(np.median(mov)) if mov.size else np.nan,
            "moving_n": int(mov.size),
            "static_late_median": float(np.median(quiet_late)) if quiet_late.size else np.nan,
            "whole_median": float(np.median(r["whole_quiet"])),
            "false_max": float(np.max(false_frac)), "false_mean": float(np.mean(false_frac)),
            "false_over": int(np.sum(np.array(false_frac) > 0.01)),
            "false_aged": int(sum(np.sum(x["s"]["false"] & (x["frame"].cloud["age"] > 1))
                                  for x in rows)),
            "false_n": int(sum(np.sum(x["s"]["false"]) for x in rows)),
            "false_per_frame": np.array([int(np.sum(x["s"]["false"])) for x in rows]),
            "rms_pull": float(np.sqrt(np.mean((err[fin] / sig[fin]) ** 2))),
            "coverage_min": float(np.min([x["s"]["coverage"] for x in rows])),
            "coverage_median": float(np.median([x["s"]["coverage"] for x in rows])),
            "coverage_under": int(np.sum(np.array([x["s"]["coverage"] for x in rows]) < 0.9)),
            "coverage_min_counts": float(np.min([
                np.sum(x["s"]["covered"] & x["s"]["lit_min_counts"])
                / max(np.sum(x["s"]["lit_min_counts"]), 1) for x in rows])),
            "uncovered_few": int(sum(np.sum(~x["s"]["covered"] & ~x["s"]["lit_min_counts"]
                                            & (x["s"]["lit_mask"])) for x in rows)),
            "uncovered": int(sum(np.sum(~x["s"]["covered"] & x["s"]["lit_mask"])
                                 for x in rows)),
            "restart_rate": float(r["restart"].mean()) if r["restart"].size else np.nan,
            "restart_n": int(r["restart"].size)}


def report(results: list[dict]) -> None:
    print(f"{'seed':>5} {'moving med':>11} {'static>=1s':>11} {'whole':>8} {'ratio':>6} "
          f"{'false max':>9} {'mean':>6} {'>1%':>4} {'RMS e/s':>8} {'cov min':>8} "
          f"{'restart':>8} {'frames':>7} {'s/frame':>8}  false points per frame: 0/1/2+")
    figs = []
    for r in results:
        f = figures(r)
        figs.append(f)
        n = len(r["rows"])
        fpf = f["false_per_frame"]
        print(f"{r['seed']:>5} {100 * f['moving_median']:>9.2f}cm "
              f"{100 * f['static_late_median']:>9.2f}cm {100 * f['whole_median']:>6.2f}cm "
              f"{f['static_late_median'] / f['whole_median']:>6.2f} "
              f"{100 * f['false_max']:>8.2f}% {100 * f['false_mean']:>5.2f}% "
              f"{f['false_over']:>4} {f['rms_pull']:>8.2f} {f['coverage_min']:>8.3f} "
              f"{100 * f['restart_rate']:>7.2f}% {n:>7} {r['t_frames'] / n:>8.3f}  "
              f"{np.sum(fpf == 0)}/{np.sum(fpf == 1)}/{np.sum(fpf >= 2)}")
    agg = {k: np.array([f[k] for f in figs]) for k in figs[0] if k != "false_per_frame"}
    ratio = agg["static_late_median"] / agg["whole_median"]
    ok = {"moving": agg["moving_median"].max() <= 0.03, "static": ratio.max() <= 1.5,
          "false": agg["false_max"].max() <= 0.01,
          "rms": 0.7 <= agg["rms_pull"].min() and agg["rms_pull"].max() <= 1.4,
          "coverage": agg["coverage_min"].min() >= 0.9}
    print("over the seeds (worst): moving median "
          f"{100 * agg['moving_median'].max():.2f} cm (target <= 3), static/whole "
          f"{ratio.max():.2f} (<= 1.5), false points in the worst frame "
          f"{100 * agg['false_max'].max():.2f} % (<= 1), RMS error/sigma "
          f"{agg['rms_pull'].min():.2f}-{agg['rms_pull'].max():.2f} (0.7-1.4), coverage of "
          f"lit pixels per frame >= {agg['coverage_min'].min():.3f} (>= 0.9)")
    print("targets held in every seed: " + ", ".join(f"{k} {'yes' if v else 'NO'}"
                                                      for k, v in ok.items()))
    per_frame = np.concatenate([f["false_per_frame"] for f in figs])
    n_frames = len(results[0]["rows"])
    hist = np.bincount(per_frame)
    print(f"false points: {agg['false_n'].sum()} over {len(figs)} x {len(results[0]['rows'])}"
          f" frames, {agg['false_aged'].sum()} of them fused (age > 1): frames over 1 %: "
          f"{agg['false_over'].sum()}; mean per frame {100 * agg['false_mean'].mean():.2f} %")
    print(f"coverage of lit pixels per frame: median {np.median(agg['coverage_median']):.3f}"
          f" (seed medians {agg['coverage_median'].min():.3f}-"
          f"{agg['coverage_median'].max():.3f}), frames below 0.9: "
          f"{agg['coverage_under'].sum()} of {agg['coverage_under'].size * n_frames}")
    print(f"lit pixels without a point that is not false: {agg['uncovered'].sum()} over all "
          f"frames, {agg['uncovered_few'].sum()} of them with fewer than {MIN_COUNTS} laser "
          "returns in the frame (min_counts); coverage of the pixels with at least "
          f"{MIN_COUNTS} returns per frame >= {agg['coverage_min_counts'].min():.3f}")
    print("false points per frame (frames with 0, 1, 2, …): "
          + ", ".join(f"{i}: {c}" for i, c in enumerate(hist)))
    n_tests = agg["restart_n"].sum()
    rate = np.nansum(agg["restart_rate"] * agg["restart_n"]) / max(n_tests, 1)
    print(f"false-restart rate on static pixels the moving objects never cross: "
          f"{100 * rate:.2f} % of {n_tests} frame points (confidence 0.997: 0.30 % per test "
          "before a first restart)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6, help="seeds 0 … N−1")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--log", type=Path, default=ROOT / "benchmarks" / "results" /
                    "bench_moving.txt")
    args = ap.parse_args()
    buf = io.StringIO()

    class Tee(io.TextIOBase):
        def write(self, s):
            sys.__stdout__.write(s)
            buf.write(s)
            return len(s)

    with redirect_stdout(Tee()):
        print(f"bench_moving: {args.seeds} seeds x {args.seconds:g} s at {args.rate:g} Hz, "
              f"background {BACKGROUND_HZ:g} Hz; CPU {cpu_model()} ({platform.machine()})")
        results = []
        for seed in range(args.seeds):
            results.append(run_seed(seed, args.seconds, args.rate))
            print(f"  seed {seed}: simulated in {results[-1]['t_sim']:.1f} s, frames in "
                  f"{results[-1]['t_frames']:.1f} s", flush=True)
        report(results)
    args.log.parent.mkdir(parents=True, exist_ok=True)
    args.log.write_text(buf.getvalue())
    print(f"log: {args.log}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
