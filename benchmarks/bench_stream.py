"""Streaming a recording larger than memory: peak resident memory and throughput (issue 7).

Writes a dense recording of at least --gigabytes GB (default 2.0; the bins of
the floodlight sample repeated under a synthetic scan trajectory, written
chunk by chunk without compression), then processes it in a fresh
subprocess with ``mems_stereo.pipeline.run.process_recording`` and prints the
wall time, pixel-slots per second, the real-time factor against the paper's
3.84 M slots/s, and the peak resident memory (ru_maxrss) of that process.

Run:  .venv/bin/python benchmarks/bench_stream.py [--gigabytes 2] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mems_stereo.io.recording import RecordingWriter, read_recording

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from mems_stereo.pipeline.run import process_recording
res = process_recording(sys.argv[1])
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "counts": res.counts, "timings": res.timings,
                  "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def make_recording(path: Path, gigabytes: float) -> int:
    src = read_recording(ROOT / "samples" / "floodlight.h5")
    s = src.system
    per_shot = s.receiver.width * s.receiver.height * 2
    n = int(math.ceil(gigabytes * 1e9 / per_shot))
    f_rep, f_mech = s.laser.f_rep, s.scanner.f_mech
    duration = n / f_rep
    # zero crossings of cos(2π f t + φ0) with φ0 = 0.3: φ = π/2 + mπ
    m = np.arange(0, int(2 * f_mech * duration) + 4)
    zc = (np.pi / 2 + m * np.pi - 0.3) / (2 * np.pi * f_mech) - 1e-3
    rising = (m % 2).astype(np.uint8)
    block = src.bins
    chunk = 16 * block.shape[0]
    tiled = np.tile(block, (16, 1, 1))
    with RecordingWriter(path, s, n, zc, rising, chunk_shots=8192) as w:
        for a in range(0, n, chunk):
            k = min(chunk, n - a)
            w.append((a + np.arange(k)) / f_rep, tiled[:k])
    return n


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gigabytes", type=float, default=2.0)
    ap.add_argument("--dir", default=None, help="where to write the recording (default: a "
                                                 "temporary directory, removed afterwards)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = Path(d) / "big.h5"
        t0 = time.perf_counter()
        n = make_recording(path, args.gigabytes)
        size = path.stat().st_size
        print(f"recording: {n} shots x 192 pixels, {size / 1e9:.2f} GB on disk, written in "
              f"{time.perf_counter() - t0:.1f} s")
        out = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True,
                             text=True, check=True, cwd=ROOT)
        r = json.loads(out.stdout.strip().splitlines()[-1])
    slots = n * 192
    print(f"processed in {r['seconds']:.1f} s (both passes): {slots / r['seconds'] / 1e6:.1f} M "
          f"slots/s, {slots / r['seconds'] / 3.84e6:.1f}x real time")
    print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in r["timings"].items()))
    print(f"peak resident memory: {r['maxrss_mb']:.0f} MB for a {size / 1e9:.2f} GB recording "
          f"(target < 500 MB)")
    print(f"counts: raw {r['counts']['raw']}, signal {r['counts']['signal']}")


if __name__ == "__main__":
    main()
