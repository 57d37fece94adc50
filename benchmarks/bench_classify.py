"""Throughput of classification + histogram formation on a dense frame (issue 7).

Prints, measured in this one run (the machines are shared: compare ratios):
  * the time of the compiled classifier + histogram pass over a dense frame
    (every pixel-slot holds a detection, as under the 6 MHz floodlight),
  * the time of a plain NumPy copy of the same bins array, in cache and from
    memory (an array larger than the last-level cache), and the ratios,
  * pixel-slots per second and the real-time factor against the paper's
    3.84 M slots/s (20,000 shots/s x 192 pixels),
  * the NumPy reference classifier on the same frame, for comparison.

Run:  .venv/bin/python benchmarks/bench_classify.py [--shots 20000]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.classify_kernel import Pass1Histograms, classify_and_accumulate
from mems_stereo.pipeline.consistency import classify_bins
from mems_stereo.pipeline.intervals import interval_table

REALTIME_SLOTS = 20000 * 192


def dense_frame(system, n_shots, rate_hz, rng):
    """First-photon codes of a constant background (every slot detects)."""
    tdc = system.tdc
    t = rng.exponential(1.0 / rate_hz, size=(n_shots, 1, 192))
    codes = np.floor(t / tdc.bin_width).astype(np.int64) + 1
    codes[codes > tdc.n_bins] = 0
    return codes.astype(np.uint16)


def _bare_histogram_py(bins, hist):
    """Per-pixel histogram only, no classification: the floor of any histogram pass."""
    K, P = bins.shape
    for k in range(K):
        for p in range(P):
            hist[p, np.int64(bins[k, p])] += 1


try:
    import numba

    _bare_histogram = numba.njit(cache=True, boundscheck=False)(_bare_histogram_py)
except ImportError:  # pragma: no cover
    _bare_histogram = _bare_histogram_py


def best_of(fn, n=5):
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=20000)
    ap.add_argument("--rate", type=float, default=6e6, help="background rate, Hz")
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    s = burkard2022()
    sc = s.scanner
    bins = dense_frame(s, args.shots, args.rate, rng)
    k = np.arange(args.shots)
    theta = sc.theta0 + sc.theta_mech_max * np.cos(2 * np.pi * sc.f_mech / s.laser.f_rep * k)
    valid = np.ones(args.shots, bool)
    print(f"dense frame: {args.shots} shots x 192 pixels, {np.mean(bins > 0) * 100:.1f} % "
          f"of slots hold a detection ({bins.nbytes / 1e6:.1f} MB of uint16)")

    t0 = time.perf_counter()
    table = interval_table(s).fill_all()
    t_table = time.perf_counter() - t0
    print(f"interval table: {table.n_steps} angle steps x 192 pixels, built in {t_table:.2f} s "
          "(once per system and setting)")

    raw = np.zeros((192, s.tdc.n_bins + 1), np.int32)
    sig = np.zeros_like(raw)
    hists = Pass1Histograms(raw, sig, np.zeros((192, table.n_steps), np.int32))
    classify_and_accumulate(bins[:8], theta[:8], valid[:8], table, s.tdc.n_bins, hists)

    def fast(labels=True):
        raw[:] = 0
        sig[:] = 0
        classify_and_accumulate(bins, theta, valid, table, s.tdc.n_bins, hists,
                                want_labels=labels)

    t_fast = best_of(fast)
    t_fast_nolab = best_of(lambda: fast(False))
    t_copy = best_of(lambda: bins.copy())
    big = np.tile(bins, (max(1, int(np.ceil(128e6 / bins.nbytes))), 1, 1))
    t_copy_mem = best_of(big.copy, 3) * bins.nbytes / big.nbytes
    big = None
    n = bins.size
    print(f"compiled classify + histograms : {t_fast * 1e3:8.2f} ms  "
          f"({n / t_fast / 1e6:7.1f} M slots/s, {n / t_fast / REALTIME_SLOTS:6.1f}x real time)")
    print(f"  without writing labels       : {t_fast_nolab * 1e3:8.2f} ms  "
          f"({n / t_fast_nolab / 1e6:7.1f} M slots/s)")
    print(f"numpy copy of the bins (cache) : {t_copy * 1e3:8.2f} ms  -> ratio "
          f"{t_fast / t_copy:6.1f}x (labels) {t_fast_nolab / t_copy:6.1f}x (histograms only)")
    print(f"numpy copy from memory (128 MB): {t_copy_mem * 1e3:8.2f} ms  -> ratio "
          f"{t_fast / t_copy_mem:6.1f}x (labels) {t_fast_nolab / t_copy_mem:6.1f}x "
          "(histograms only)")
    hist = np.zeros((192, s.tdc.n_bins + 1), np.int32)
    b2 = bins.reshape(bins.shape[0], -1)
    _bare_histogram(b2[:4], hist)
    t_bare = best_of(lambda: _bare_histogram(b2, hist))
    print(f"bare per-pixel histogram only  : {t_bare * 1e3:8.2f} ms  -> ratio "
          f"{t_bare / t_copy:6.1f}x (cache copy) {t_bare / t_copy_mem:6.1f}x (memory copy): the "
          "scatter into 192 x 4097 counters alone exceeds 3x a copy")
    m = min(args.shots, 2000)
    t_ref = best_of(lambda: classify_bins(s, bins[:m], theta[:m], valid[:m]), 1) * args.shots / m
    print(f"numpy reference classifier     : {t_ref * 1e3:8.0f} ms (extrapolated from {m} "
          f"shots) -> compiled path is {t_ref / t_fast:.0f}x faster")


if __name__ == "__main__":
    main()
