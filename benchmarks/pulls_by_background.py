"""Signed error/σ of a sweep's points by range band and background rate.

Reads the points that ``bench_scenarios.py --dump FILE.npz`` saved (one file or
several, joined) and prints, per range band and background band, the median
error/σ of the fused point and of its time-of-flight and stereo estimates
(each against its own σ) with their median error in cm: a lean of one
estimate, which an RMS near 1 hides, shows here (docs/accuracy.md, "Scenario sweep").

    .venv/bin/python benchmarks/bench_scenarios.py --cases 50 --seed 28000 --dump s28000.npz
    .venv/bin/python benchmarks/pulls_by_background.py s28000.npz
"""

from __future__ import annotations

import argparse

import numpy as np

RANGE_BANDS = ((0.0, 1.0), (1.0, 3.0), (3.0, 6.0), (6.0, np.inf))
BACKGROUND_BANDS = ((0.0, 1e5), (1e5, 1e6), (1e6, 3e6), (3e6, 1e7), (1e7, np.inf))
FIELDS = ("err", "sigma", "r_true", "background_hz", "attr_range_tof", "attr_sigma_r_tof",
          "attr_range_stereo", "attr_sigma_r_stereo")


def load(paths) -> dict:
    """The joined columns of :data:`FIELDS` from the dump files ``paths``."""
    data = [np.load(p) for p in paths]
    return {k: np.concatenate([d[k] for d in data]) for k in FIELDS}


def table(a: dict, min_points: int = 20) -> list[str]:
    """Markdown rows: range band, background band, points, median error/σ (fused, ToF,
    stereo) and median error (cm) of the ToF and stereo estimates."""
    rt, bg = a["r_true"], a["background_hz"]
    d_tof, d_st = a["attr_range_tof"] - rt, a["attr_range_stereo"] - rt
    with np.errstate(invalid="ignore", divide="ignore"):
        z = a["err"] / a["sigma"]
        z_tof, z_st = d_tof / a["attr_sigma_r_tof"], d_st / a["attr_sigma_r_stereo"]
    rows = ["| range m | background MHz | points | fused error/σ | ToF error/σ (cm) "
            "| stereo error/σ (cm) |", "| --- | --- | --- | --- | --- | --- |"]
    for lo, hi in RANGE_BANDS:
        for blo, bhi in BACKGROUND_BANDS:
            m = ((rt >= lo) & (rt < hi) & (bg >= blo) & (bg < bhi) & np.isfinite(z_tof)
                 & np.isfinite(z_st))
            if m.sum() < min_points:
                continue
            rows.append(f"| {lo:g}–{hi:g} | {blo / 1e6:g}–{bhi / 1e6:g} | {int(m.sum())} "
                        f"| {np.median(z[m]):+.2f} | {np.median(z_tof[m]):+.2f} "
                        f"({100 * np.median(d_tof[m]):+.1f}) | {np.median(z_st[m]):+.2f} "
                        f"({100 * np.median(d_st[m]):+.1f}) |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dumps", nargs="+", help="files written by bench_scenarios.py --dump")
    ap.add_argument("--min-points", type=int, default=20,
                    help="leave out cells with fewer points (default 20)")
    args = ap.parse_args(argv)
    print("\n".join(table(load(args.dumps), args.min_points)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
