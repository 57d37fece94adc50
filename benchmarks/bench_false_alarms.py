"""The peak detector's false alarms on background alone (issue 13, docs/accuracy.md).

Draws the systems, shot counts and backgrounds of the scenario sweep's family
(:func:`bench_scenarios.draw_case`: 10 kHz–30 MHz, 400–400,000 shots ×
``--scale``) but images a black scene (a wall of reflectivity 1e-9 at 500 m),
processes each recording with the defaults and prints, per case, the pixels
whose strongest footprint window reaches a Bonferroni p-value (Poisson tail ×
window positions) below 0.1, 0.01, 10⁻³, and the peaks and points that the
detector kept.  Summary: the observed fraction of pixels below each level
against the level (what the threshold promises, per pixel) and the peaks per
frame (recording) against the per-frame budgets.

    .venv/bin/python benchmarks/bench_false_alarms.py --cases 40 --seed 30000
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402
from scipy.special import pdtrc  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from bench_scenarios import DARK_HZ, draw_case  # noqa: E402

import mems_stereo.pipeline.matched as matched_mod  # noqa: E402
import mems_stereo.pipeline.peaks as peaks_mod  # noqa: E402
from mems_stereo.pipeline.peak_support import scan_sf  # noqa: E402
from mems_stereo.pipeline.run import process_recording  # noqa: E402
from mems_stereo.sim import scene_from_dict, simulate  # noqa: E402

BLACK = {"objects": [{"type": "plane", "center": [0, 0, 500.0], "normal": [0, 0, -1],
                      "size": [2000, 30], "reflectivity": 1e-9}]}
LEVELS = (0.5, 0.1, 0.01, 1e-3)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--seed", type=int, default=30000)
    ap.add_argument("--scale", type=float, default=1.0)
    args = ap.parse_args(argv)

    seen = []
    seen_scan = []
    orig = peaks_mod.window_scores

    def recording(*a, **k):
        out = orig(*a, **k)
        cnt, mu, n_windows = out.cnt, out.mu, out.n_windows
        with np.errstate(invalid="ignore"):
            p = pdtrc(np.maximum(cnt - 1, 0), np.maximum(mu, 1e-12)) * n_windows
        seen.append(np.where(cnt >= 1, p, 1.0))
        seen_scan.append(np.where(cnt >= 1, scan_sf(cnt, np.maximum(mu, 1e-12),
                                                              n_windows), 1.0))
        return out

    peaks_mod.window_scores = recording
    boxes = []  # the matched filter's best box per candidate: (Bonferroni p, scan p)
    orig_box = matched_mod.scan_box_sf

    def recording_box(k, mu, n_windows, n_code_pos):  # (arrays: a frame's candidates)
        p = orig_box(k, mu, n_windows, n_code_pos)
        bon = (pdtrc(np.maximum(np.asarray(k) - 1, 0), np.maximum(mu, 1e-12)) * n_windows
               * n_code_pos)
        boxes.extend(zip(np.atleast_1d(bon).tolist(), np.atleast_1d(p).tolist()))
        return p

    matched_mod.scan_box_sf = recording_box
    # the same levels for the first stage's scan p-value (scan_sf)
    below_scan = np.zeros(len(LEVELS))
    scene = scene_from_dict(BLACK)
    below = np.zeros(len(LEVELS))
    n_pix = 0
    peaks_per = []
    print(f"{'seed':>6} {'shots':>8} {'bg MHz':>7} " + " ".join(f"p<{x:g}".rjust(7) for x in LEVELS)
          + f" {'peaks':>5} {'points':>6} {'cpu s':>6}")
    for i in range(args.cases):
        case = draw_case(args.seed + i, args.scale)
        t0 = time.process_time()
        rec = simulate(case.system, scene, case.shots, rng=np.random.default_rng(case.seed),
                       background_hz=case.background_hz, dark_count_hz=DARK_HZ)
        seen.clear()
        seen_scan.clear()
        res = process_recording(rec)
        p = np.concatenate(seen) if seen else np.ones(0)
        ps = np.concatenate(seen_scan) if seen_scan else np.ones(0)
        below_scan += [np.sum(ps < x) for x in LEVELS]
        cnt = np.array([np.sum(p < x) for x in LEVELS])
        below += cnt
        n_pix += p.size
        peaks_per.append(len(res.peaks))
        print(f"{case.seed:>6} {case.shots:>8} {case.background_hz / 1e6:>7.3f} "
              + " ".join(f"{c:>7d}" for c in cnt)
              + f" {len(res.peaks):>5d} {len(res.cloud):>6d} {time.process_time() - t0:>6.1f}",
              flush=True)
    print(f"\n{args.cases} recordings, {n_pix} pixels (background only)")
    for x, b in zip(LEVELS, below):
        print(f"  Bonferroni p < {x:g}: {int(b)} pixels, {b / max(n_pix, 1):.2e} per pixel "
              f"(promised ≤ {x:g}; ratio {b / max(n_pix, 1) / x:.2f})")
    for x, b in zip(LEVELS, below_scan):
        print(f"  scan p (first-order clumping) < {x:g}: {int(b)} pixels, "
              f"{b / max(n_pix, 1):.2e} per pixel (ratio {b / max(n_pix, 1) / x:.2f})")
    bx = np.asarray(boxes).reshape(-1, 2)
    print(f"  matched filter: {len(bx)} candidates scored (of {n_pix} pixels)")
    for x in LEVELS:
        nb, ns = int(np.sum(bx[:, 0] < x)), int(np.sum(bx[:, 1] < x))
        print(f"    box p < {x:g}: Bonferroni {nb} ({nb / max(n_pix, 1):.2e} per pixel), "
              f"scan {ns} ({ns / max(n_pix, 1):.2e} per pixel)")
    pp = np.asarray(peaks_per)
    print(f"  peaks kept: {int(pp.sum())} in {pp.size} frames ({pp.mean():.3f} per frame; "
          f"frames with any: {int(np.sum(pp > 0))})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
