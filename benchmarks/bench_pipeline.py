"""Figures of the core pipeline on the samples (issue 4, "What must show").

Prints, measured in this one run on samples/room.h5 (100 kHz background,
800 shots) and samples/floodlight.h5 (6 MHz, 3200 shots):

1. the paper's pattern: raw counts, signal counts, shots, and whether each
   clearly returning pixel's peak code in the raw histogram is the same in the
   signal histogram (and how much of the peak's height classification kept);
2. signal recall and noise rejection against ``/truth/label`` for
   (a) our classifier (``process_recording``), (b) the raw histogram with the
   paper's moving-average filter, a background-grounded Poisson threshold and
   the peak detector (detections in each pixel's peak window are signal),
   (c) Open3D's statistical outlier removal on the raw per-detection points;
3. point accuracy against the true scene (ray cast through each point),
   coverage of the illuminated pixels, and each estimate's error against its
   own reported σ; for the floodlight also with the ``min_range`` prior and a
   looser peak false-alarm probability (``VARIANTS``);
4. the time of each stage.

Tables are Markdown, ready for docs/accuracy.md.

Run:  .venv/bin/python benchmarks/bench_pipeline.py [--samples DIR]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

from mems_stereo.geometry.uncertainty import tof_pixel_point
from mems_stereo.io.recording import read_recording
from mems_stereo.model.tdc import path_length_from_codes
from mems_stereo.physics.background import (
    background_rate_mle,
    expected_background,
    moving_sum,
    poisson_threshold,
)
from mems_stereo.pipeline.histograms import moving_average
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from oracles import detect_peaks  # noqa: E402  (the paper's detector, kept as a test oracle)

SAMPLES = (("room", "room.h5", "room_scene.json"),
           ("floodlight", "floodlight.h5", "room_scene.json"))
TARGETS = {"room": (0.98, 0.97), "floodlight": (0.97, 0.92)}
MAX_TRUE_RANGE = 6.0        # m, accuracy is evaluated for targets within this range
MEDIAN_ERROR_TARGET = 0.03  # m
COVERAGE_TARGET = 0.5
SIGMA_RATIO_LIMIT = 1.5
GAUSS_MAD = 0.6745          # median |z| of a standard normal
# non-default settings also measured (accuracy table): the min_range prior and
# a looser peak false-alarm probability
VARIANTS = {"floodlight": (Settings(min_range=1.0), Settings(min_range=1.0, false_alarm=0.1))}


# --------------------------------------------------------------------------- helpers
def filter_width(system) -> int:
    """The paper's moving-average width: the pulse FWHM in bins, odd (49 for 14.9 ns / 312.5 ps)."""
    w = max(1, int(round(system.laser.pulse_fwhm / system.tdc.bin_width)))
    return w + 1 - w % 2


def scores(truth_label, labels) -> tuple[float, float]:
    """(recall, noise rejection) of labels against truth labels, both (K, H, W).

    Recall: share of truth-signal (1) detections labelled 1; noise rejection:
    share of truth-background (2) detections labelled 2.
    """
    t = np.asarray(truth_label)
    a = np.asarray(labels)
    return float(np.mean(a[t == 1] == 1)), float(np.mean(a[t == 2] == 2))


def raw_histogram_peaks(raw, n_shots: int, bin_width: float, width: int,
                        p_false_alarm: float):
    """Strongest peak per pixel of the raw histogram: filter, Poisson threshold, detector.

    ``raw`` : (H, W, n_bins) counts of every detection (index j = code j+1).
    The background rate is the pile-up-aware MLE (``background_rate_mle``) of
    the raw histogram, re-estimated once with each pixel's first peak window
    (±width bins) excluded so the return does not raise it.  The threshold is
    ``poisson_threshold`` of ``expected_background`` of that rate at
    ``p_false_alarm`` per window position.

    Returns ``code`` (H, W) int64 (0 = no peak) and ``rate`` (H, W) Hz.
    """
    H, W, n_bins = raw.shape
    smooth = moving_average(raw, width)
    j = np.arange(n_bins)
    rate = background_rate_mle(raw, n_shots, bin_width)
    code = np.zeros((H, W), np.int64)
    for _ in range(2):
        thr = poisson_threshold(expected_background(rate, n_shots, bin_width, n_bins), width,
                                p_false_alarm)
        code, _v = detect_peaks(smooth, thr, min_separation=width, max_peaks=1).strongest((H, W))
        excl = (code[..., None] > 0) & (np.abs(j + 1 - code[..., None]) <= width)
        rate = background_rate_mle(raw, n_shots, bin_width, exclude=excl, raw=raw)
    return code, rate


def window_labels(bins, code, half_width: int) -> np.ndarray:
    """Labels of detections from per-pixel peak windows: 1 inside ``code ± half_width``, else 2.

    ``bins`` (K, H, W) codes (0 = none), ``code`` (H, W) (0 = no peak).
    Returns (K, H, W) uint8 (0 where no detection).
    """
    b = bins.astype(np.int64)
    inside = (code[None] > 0) & (np.abs(b - code[None]) <= half_width)
    return np.where(b == 0, 0, np.where(inside, 1, 2)).astype(np.uint8)


def detection_pixel_points(system, bins) -> tuple[np.ndarray, tuple]:
    """Each detection's point on its pixel ray at its path length (a plain dtof camera).

    Returns ``points`` (M, 3) float64 m, receiver frame (NaN where L ≤ |b|),
    and the index tuple (shot, row, col) of the M detections.
    """
    idx = np.nonzero(bins)
    L = path_length_from_codes(bins[idx], system.tdc, system.speed_of_light)
    u = idx[2].astype(np.float64)
    v = idx[1].astype(np.float64)
    return tof_pixel_point(system, u, v, L, np.zeros_like(L)), idx


def sor_labels(system, bins, nb_neighbors: int = 20, std_ratio: float = 2.0) -> np.ndarray:
    """Open3D statistical outlier removal on the per-detection pixel-ray points.

    Inliers are labelled 1, outliers and points without a solution (L ≤ |b|) 2.
    Returns (K, H, W) uint8 (0 where no detection).
    """
    import open3d as o3d

    pts, idx = detection_pixel_points(system, bins)
    ok = np.all(np.isfinite(pts), axis=1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[ok]))
    _, keep = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    lab_ok = np.full(int(ok.sum()), 2, np.uint8)
    lab_ok[np.asarray(keep, dtype=np.int64)] = 1
    lab = np.full(pts.shape[0], 2, np.uint8)
    lab[ok] = lab_ok
    out = np.zeros(bins.shape, np.uint8)
    out[idx] = lab
    return out


def true_ranges(scene, points) -> np.ndarray:
    """Range of the true surface along the ray from the origin through each point, m (inf: none)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    return scene.cast(np.zeros(3), d).t


def sigma_ratios(err, sigma) -> tuple[float, float]:
    """(RMS error / RMS σ, median |error/σ| / 0.6745): both 1 for honest Gaussian σ."""
    err = np.asarray(err, float)
    sigma = np.asarray(sigma, float)
    return (float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(sigma ** 2))),
            float(np.median(np.abs(err) / sigma) / GAUSS_MAD))


def cloud_accuracy(cloud, scene, illuminated) -> dict:
    """Errors of a peak cloud against the true scene, per estimate, and coverage.

    ``illuminated`` (H, W) bool: pixels with at least one truth-signal
    detection.  The true range of a point is the scene's first hit on the ray
    from the origin through the (fused) point; the stereo and ToF ranges are
    compared with the same true range.  Only points with a true range within
    ``MAX_TRUE_RANGE`` enter the error statistics.
    """
    r_true = true_ranges(scene, cloud.points)
    near = np.isfinite(r_true) & (r_true <= MAX_TRUE_RANGE)
    has_pt = np.zeros(illuminated.shape, bool)
    has_pt[cloud["row"], cloud["pixel"]] = True
    acc = {"points": len(cloud), "near": int(near.sum()),
           "illuminated": int(illuminated.sum()), "covered": int(np.sum(illuminated & has_pt))}
    acc["coverage"] = acc["covered"] / acc["illuminated"] if acc["illuminated"] else float("nan")
    for est, rk, sk in (("fused", "range", "sigma_r"), ("stereo", "range_stereo",
                                                          "sigma_r_stereo"),
                        ("ToF", "range_tof", "sigma_r_tof")):
        e = (cloud[rk] - r_true)[near]
        s = cloud[sk][near]
        rms_ratio, med_ratio = sigma_ratios(e, s)
        acc[est] = {"median_abs": float(np.median(np.abs(e))), "mean": float(np.mean(e)),
                    "rms": float(np.sqrt(np.mean(e ** 2))),
                    "rms_sigma": float(np.sqrt(np.mean(s ** 2))),
                    "rms_ratio": rms_ratio, "median_ratio": med_ratio,
                    "beyond_3sigma": int(np.sum(np.abs(e) > 3 * s))}
    e_f = np.abs(cloud["range"] - r_true)[near]
    acc["within_10cm"] = int(np.sum(e_f <= 0.10))
    acc["p90_abs"] = float(np.percentile(e_f, 90)) if e_f.size else float("nan")
    return acc


# --------------------------------------------------------------------------- one sample
def evaluate(name: str, path: Path, scene_path: Path, variants=(), system=None) -> dict:
    """Process one sample with ``system`` (default: the file's /system) and measure
    every figure; returns a dict of results.  The alternatives use the same system."""
    from mems_stereo.sim.scene import load_scene

    t0 = time.perf_counter()
    res = process_recording(path, system=system)
    t_process = time.perf_counter() - t0
    rec = read_recording(path)
    system = rec.system if system is None else system
    truth = rec.truth["label"]
    K, H, W = rec.bins.shape
    n_bins = system.tdc.n_bins
    width = filter_width(system)
    raw = res.histograms["raw"]
    sig = res.histograms["signal"]
    out = {"name": name, "shots": K, "counts": res.counts, "timings": dict(res.timings),
           "t_process": t_process, "width": width}
    out["raw_256"] = int(raw[..., :256].sum())
    out["signal_256"] = int(sig[..., :256].sum())

    # (b) raw histogram: filter, background-grounded threshold, peaks.  The
    # false-alarm convention is the pipeline's: Settings.false_alarm per pixel,
    # shared over the n_bins / width independent window positions.
    t = time.perf_counter()
    p_fa = Settings().false_alarm * width / n_bins
    code_raw, _rate = raw_histogram_peaks(raw, K, system.tdc.bin_width, width, p_fa)
    lab_raw = window_labels(rec.bins, code_raw, width)
    out["t_raw_hist"] = time.perf_counter() - t
    out["p_fa"] = p_fa

    # 1. pattern: is the raw peak of each clearly returning pixel kept in S?
    clear = code_raw > 0
    rr, cc = np.nonzero(clear)
    c_raw = code_raw[clear]
    code_s = np.argmax(moving_average(sig, width), axis=-1)[clear] + 1  # same filter on S
    code_p = np.zeros((H, W), np.int64)                              # the pipeline's peaks
    code_p[res.peaks.row, res.peaks.col] = res.peaks.code
    code_p = code_p[clear]
    d_s = code_s - c_raw
    has_p = code_p > 0
    d_p = (code_p - c_raw)[has_p]
    h_raw = moving_sum(raw, width)[rr, cc, c_raw - 1]  # counts in the width-bin window
    h_sig = moving_sum(sig, width)[rr, cc, c_raw - 1]
    out["pattern"] = {
        "clear_pixels": int(clear.sum()),
        "same_s": int(np.sum(d_s == 0)), "within2_s": int(np.sum(np.abs(d_s) <= 2)),
        "max_shift_s": int(np.abs(d_s).max()) if d_s.size else 0,
        "with_peak": int(has_p.sum()), "within2_p": int(np.sum(np.abs(d_p) <= 2)),
        "median_shift_p": float(np.median(np.abs(d_p))) if d_p.size else float("nan"),
        "max_shift_p": int(np.abs(d_p).max()) if d_p.size else 0,
        "height_raw": int(h_raw.sum()), "height_sig": int(h_sig.sum()),
    }
    # the two highest clear peaks (the paper's Fig. 8 quotes pixels 14 and 81)
    top = np.argsort(-h_raw, kind="stable")[:2]
    out["pattern"]["top"] = [(int(cc[i]), int(c_raw[i]), int(h_raw[i]), int(h_sig[i]))
                             for i in top]

    # 2. classification scores
    tr = res.truth
    out["ours"] = (tr["recall"], tr["noise_rejection"])
    out["raw_hist"] = scores(truth, lab_raw)
    t = time.perf_counter()
    lab_sor = sor_labels(system, rec.bins)
    out["t_sor"] = time.perf_counter() - t
    out["sor"] = scores(truth, lab_sor)

    # 3. accuracy of the cloud against the true scene
    t = time.perf_counter()
    scene = load_scene(scene_path)
    illum = np.any(truth == 1, axis=0)
    acc = cloud_accuracy(res.cloud, scene, illum)
    out["accuracy"] = acc
    out["t_truth"] = time.perf_counter() - t
    out["variants"] = []
    for st in variants:
        rv = process_recording(path, system=system, settings=st)
        out["variants"].append((st, rv.truth, rv.counts, cloud_accuracy(rv.cloud, scene, illum)))
    return out


# --------------------------------------------------------------------------- printing
def _ok(flag: bool) -> str:
    return "met" if flag else "**missed**"


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _head(cells) -> str:
    return _row(cells) + "\n" + _row(["---"] * len(cells))


def print_tables(results: list[dict]) -> None:
    by = {r["name"]: r for r in results}
    width = results[0]["width"]
    print("\n### 1. The paper's pattern (Fig. 8: room light, 800 shots)\n")
    print(_head(["sample", "shots", "raw counts", "signal counts", "raw / signal",
                 "raw, codes 1–256", "signal, codes 1–256"]))
    for r in results:
        c = r["counts"]
        print(_row([r["name"], r["shots"], f"{c['raw']:,}", f"{c['signal']:,}",
                    f"{c['raw'] / c['signal']:.1f}", f"{r['raw_256']:,}",
                    f"{r['signal_256']:,}"]))
    print(f"\nPixels with a clear return = a peak of the raw histogram above the Poisson "
          f"threshold (method (b) below). Peak code of S: the same {width}-bin filter, "
          f"strongest bin; pipeline peak: `ProcessResult.peaks`. Heights: counts in the "
          f"{width}-bin window at the raw peak.\n")
    print(_head(["sample", "clear pixels", "S peak = raw peak", "S peak within ±2 codes",
                 "max shift", "pipeline peak found", "pipeline peak within ±2 codes",
                 "median / max shift", "window counts raw → signal"]))
    for r in results:
        p = r["pattern"]
        print(_row([r["name"], p["clear_pixels"], p["same_s"], p["within2_s"],
                    p["max_shift_s"], p["with_peak"], p["within2_p"],
                    f"{p['median_shift_p']:.0f} / {p['max_shift_p']}",
                    f"{p['height_raw']:,} → {p['height_sig']:,}"]))
    for r in results:
        tops = "; ".join(f"pixel {c} at code {k}: {a} → {b}" for c, k, a, b in
                         r["pattern"]["top"])
        print(f"\n{r['name']}, the two highest raw peaks (window counts raw → signal): {tops}.")

    print("\n### 2. Signal recall / noise rejection against /truth/label\n")
    print(_head(["method", "room recall", "room rejection", "floodlight recall",
                 "floodlight rejection"]))
    rows = (("(a) ours: consistency test (`process_recording`, defaults)", "ours"),
            (f"(b) raw histogram: moving average ({width} bins), Poisson threshold on the "
             f"pile-up MLE background (p_fa {results[0]['p_fa']:.1e} per position), "
             f"strongest peak ± {width} codes", "raw_hist"),
            ("(c) Open3D `remove_statistical_outlier(20, 2.0)` on per-detection pixel-ray "
             "points", "sor"))
    for label, key in rows:
        cells = [label]
        for nm in ("room", "floodlight"):
            cells += ([f"{by[nm][key][0]:.4f}", f"{by[nm][key][1]:.4f}"] if nm in by
                      else ["–", "–"])
        print(_row(cells))
    print()
    for r in results:
        rc, rj = r["ours"]
        tr, tj = TARGETS[r["name"]]
        print(f"- {r['name']}: ours recall {rc:.4f} (target ≥ {tr}: {_ok(rc >= tr)}), "
              f"rejection {rj:.4f} (target ≥ {tj}: {_ok(rj >= tj)})")

    print(f"\n### 3. Point accuracy against the true scene (true range ≤ {MAX_TRUE_RANGE:g} m)\n")
    print(_head(["sample", "settings", "recall / rejection", "points", "points ≤ 6 m",
                 "illuminated pixels", "covered", "coverage", "median abs. error",
                 "90th pct.", "within 10 cm"]))
    for r in results:
        rows = [(r["settings"], (r["ours"][0], r["ours"][1]), r["accuracy"])]
        rows += [(st, (tr["recall"], tr["noise_rejection"]), a)
                 for st, tr, _c, a in r["variants"]]
        for st, (rc, rj), a in rows:
            print(_row([r["name"], _settings_str(st), f"{rc:.4f} / {rj:.4f}", a["points"],
                        a["near"], a["illuminated"], a["covered"], f"{a['coverage']:.2f}",
                        f"{a['fused']['median_abs'] * 100:.1f} cm",
                        f"{a['p90_abs'] * 100:.1f} cm", a["within_10cm"]]))
    print("\nEach estimate against its own reported σ (defaults; points with true range "
          "≤ 6 m):\n")
    print(_head(["sample", "estimate", "median abs. error", "mean error", "RMS error",
                 "RMS σ", "RMS error / RMS σ", "median abs(error/σ) / 0.674",
                 "points beyond 3σ"]))
    for r in results:
        a = r["accuracy"]
        for est in ("fused", "stereo", "ToF"):
            e = a[est]
            print(_row([r["name"], est, f"{e['median_abs'] * 100:.1f} cm",
                        f"{e['mean'] * 100:+.1f} cm", f"{e['rms'] * 100:.1f} cm",
                        f"{e['rms_sigma'] * 100:.1f} cm", f"{e['rms_ratio']:.2f}",
                        f"{e['median_ratio']:.2f}", f"{e['beyond_3sigma']} / {a['near']}"]))
    print()
    for r in results:
        a = r["accuracy"]
        bad = [f"{est} {k}" for est in ("fused", "stereo", "ToF")
               for k in ("rms_ratio", "median_ratio")
               if not (1 / SIGMA_RATIO_LIMIT <= a[est][k] <= SIGMA_RATIO_LIMIT)]
        print(f"- {r['name']} (defaults): median error {a['fused']['median_abs'] * 100:.1f} cm "
              f"(target ≤ 3 cm: {_ok(a['fused']['median_abs'] <= MEDIAN_ERROR_TARGET)}), "
              f"coverage {a['coverage']:.2f} (target ≥ 0.5: "
              f"{_ok(a['coverage'] >= COVERAGE_TARGET)}), ratios within 1.5×: {_ok(not bad)}"
              + (f" (outside: {', '.join(bad)})" if bad else ""))

    print("\n### 4. Time per stage (s, this run, defaults)\n")
    stages = list(results[0]["timings"])
    print(_head(["sample"] + stages + ["process_recording total", "(b) raw histogram",
                                       "(c) Open3D SOR incl. points", "truth ray casts"]))
    for r in results:
        print(_row([r["name"]] + [f"{r['timings'][s]:.3f}" for s in stages]
                   + [f"{r['t_process']:.3f}", f"{r['t_raw_hist']:.3f}", f"{r['t_sor']:.3f}",
                      f"{r['t_truth']:.3f}"]))


def _settings_str(st) -> str:
    if st is None or st == Settings():
        return "defaults"
    d = Settings()
    parts = [f"{k}={getattr(st, k)}" for k in ("confidence", "min_range", "false_alarm",
                                                "min_counts")
             if getattr(st, k) != getattr(d, k)]
    return ", ".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=Path, default=ROOT / "samples",
                    help="directory holding room.h5, floodlight.h5, room_scene.json")
    ap.add_argument("--only", choices=[s[0] for s in SAMPLES], default=None)
    ap.add_argument("--system", default=None,
                    help="system JSON to process with (default: the samples' true system, "
                         "calib_true_system.json, where present: the recordings' /system is "
                         "the nominal one, which calibration corrects; 'nominal': the files')")
    args = ap.parse_args(argv)
    from mems_stereo.model.system import load_system

    true_file = args.samples / "calib_true_system.json"
    if args.system == "nominal" or (args.system is None and not true_file.exists()):
        system, which = None, "each recording's /system (nominal)"
    else:
        f = Path(args.system) if args.system else true_file
        system, which = load_system(f), str(f)
    t0 = time.perf_counter()
    results = []
    for name, rec_file, scene_file in SAMPLES:
        if args.only and name != args.only:
            continue
        r = evaluate(name, args.samples / rec_file, args.samples / scene_file,
                     VARIANTS.get(name, ()), system)
        r["settings"] = None
        results.append(r)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, NumPy {np.__version__}")
    print(f"processed with: {which}")
    print_tables(results)
    print(f"\ntotal run time of this script: {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
