"""Streaming throughput and memory on one core (issues 7 and 14).

1. Streaming a recording larger than memory (issue 7): writes a dense
   recording of at least --gigabytes GB (default 2.0; the bins of the
   floodlight sample repeated under a synthetic scan trajectory, written chunk
   by chunk without compression), then processes it in a fresh subprocess with
   ``mems_stereo.pipeline.run.process_recording`` and prints the wall time,
   pixel-slots per second, the real-time factor against the paper's 3.84 M
   slots/s, and the peak resident memory (ru_maxrss) of that process.
2. Dense floodlight recordings (issue 14): for each of --dense-shots (default
   200,000 and 2,000,000 shots) a recording SIMULATED with its own seed
   (``benchmarks/_dense.py``: 6 MHz background, the room scene, gzip chunks of
   1024 shots, no truth), then in fresh processes: the time to read and copy
   its bins, and ``process_recording`` end to end (header to cloud, after the
   imports) with the interval-table disk cache empty (cold) and filled (warm,
   as every later recording of the same system), each with its peak RSS;
   printed against the targets (≤ 4× read + copy, ≥ 20× real time, ≤ 400 MB).
3. Startup: runs 2 to 6 of ``mems-stereo process samples/room.h5`` (a private table
   cache, filled by the first)
   (wall and CPU seconds, interpreter start included), the heavy modules that
   run loads (none: the PLY is written by NumPy, small recordings load no
   numba), and the import times of NumPy, the package, the pipeline and
   Open3D (off the process path, for reference).

Run:  .venv/bin/python benchmarks/bench_stream.py [--gigabytes 2] [--dense-shots 200000 2000000]
      [--dir /tmp] [--before COMMIT]   (--gigabytes 0 or --dense-shots with no number skip a part)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _dense import (  # noqa: E402
    PACKAGE_PRELUDE,
    make_dense_recording,
    measure_child,
    read_copy_seconds,
)

from mems_stereo.io.recording import RecordingWriter, read_recording  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_READ_RATIO, TARGET_REALTIME, TARGET_RSS_MB = 4.0, 20.0, 400.0

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from mems_stereo.pipeline.run import process_recording
res = process_recording(sys.argv[1])
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "counts": dict(res.counts), "timings": res.timings,
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


PROCESS = PACKAGE_PRELUDE + r"""
t0 = time.perf_counter()
from mems_stereo.pipeline.run import process_recording
t1 = time.perf_counter()
c1 = time.process_time()
res = process_recording(sys.argv[1])
t2 = time.perf_counter()
import mems_stereo
import numpy as np
c = res.cloud
np.savez(sys.argv[2], points=c.points, **{k: np.asarray(v) for k, v in c.attributes.items()})
print(json.dumps({"import_s": t1 - t0, "seconds": t2 - t1, "cpu_s": time.process_time() - c1,
                  "counts": dict(res.counts), "timings": res.timings,
                  "package": mems_stereo.__file__}))
"""


def compare_clouds(a_path, b_path) -> str:
    """Whether two saved clouds are equal bit for bit, else their largest differences."""
    a, b = np.load(a_path), np.load(b_path)
    if sorted(a.files) != sorted(b.files) or a["points"].shape != b["points"].shape:
        return f"DIFFERENT attributes or sizes ({a['points'].shape} vs {b['points'].shape})"
    if all(np.array_equal(a[k], b[k], equal_nan=True) for k in a.files):
        return (f"identical bit for bit ({a['points'].shape[0]} points, "
                f"{len(a.files) - 1} attributes)")
    dp = float(np.nanmax(np.abs(a["points"] - b["points"])))
    rel = max(float(np.nanmax(np.abs(a[k] - b[k]) / np.maximum(np.abs(a[k]), 1e-300)))
              for k in a.files if k != "points")
    return f"NOT bit-identical: points differ by up to {dp:.3g} m, attributes by {rel:.3g} relative"


def dense(shots: int, seed: int, d: Path, runs=("cold", "warm"), before=None) -> None:
    path = d / f"dense{shots}.h5"
    t0 = time.perf_counter()
    info = make_dense_recording(path, shots, seed)
    real = shots / info["f_rep"]
    print(f"\ndense floodlight, simulated (seed {seed}): {shots} shots x 192 pixels = "
          f"{real:.0f} s of recording at 20 kHz, {info['bins_bytes'] / 1e6:.0f} MB of bins, "
          f"{info['bytes_on_disk'] / 1e6:.0f} MB gzip'd on disk (made in "
          f"{time.perf_counter() - t0:.0f} s)")
    t_read, c_read = read_copy_seconds(path)
    print(f"  read + copy its bins (h5py, zlib): {t_read:.2f} s ({c_read:.2f} s CPU); the "
          f"ratios below are against this")
    try:
        t_fast, c_fast = read_copy_seconds(path, "libdeflate")
        print(f"  read + copy its bins with libdeflate (the pipeline's reader): {t_fast:.2f} s "
              f"({c_fast:.2f} s CPU)")
    except RuntimeError:
        c_fast = None
        print("  (no libdeflate here: the pipeline reads with h5py)")
    cache = d / f"cache{shots}"
    env = dict(os.environ, MEMS_STEREO_CACHE=str(cache))
    if "cold" not in runs:  # fill the cache here (the rows every recording of the system needs)
        from mems_stereo.model.system import burkard2022
        from mems_stereo.pipeline.intervals import IntervalTable
        from mems_stereo.pipeline.settings import Settings

        os.environ["MEMS_STEREO_CACHE"] = str(cache)
        IntervalTable.for_settings(burkard2022(), Settings()).fill_all().save_cache()
    labels = [(f"{r} table cache", env) for r in runs]
    if before:  # the same recording and cache with the package of another commit
        labels.insert(0, (f"BEFORE ({before}), {runs[-1]} table cache",
                          dict(env, BENCH_PACKAGE_SRC=str(extract_commit(before, d)))))
    if before:  # its numba kernels compiled into their disk cache first (a package
        # extracted to a new path has none: its first run would pay the JIT, ~2 s)
        measure_child(PROCESS, path, d / "warmup.npz", env=labels[0][1])
    clouds = []
    for label, env_ in labels:
        clouds.append(d / f"cloud{len(clouds)}.npz")
        r = measure_child(PROCESS, path, clouds[-1], env=env_)
        t = r["seconds"]
        ok = (t <= TARGET_READ_RATIO * t_read, real / t >= TARGET_REALTIME,
              r["maxrss_mb"] <= TARGET_RSS_MB)
        print(f"  process_recording, {label}: {t:.2f} s = {t / t_read:.1f}x read+copy "
              f"(target <= {TARGET_READ_RATIO:g}x: {'met' if ok[0] else 'NOT met'}), "
              f"{real / t:.1f}x real time (target >= {TARGET_REALTIME:g}x: "
              f"{'met' if ok[1] else 'NOT met'}), peak RSS {r['maxrss_mb']:.0f} MB (target <= "
              f"{TARGET_RSS_MB:g}: {'met' if ok[2] else 'NOT met'}); imports "
              f"{r['import_s']:.2f} s before")
        vs_fast = ("" if c_fast is None else
                   f" ({r['cpu_s'] / c_fast:.1f}x the libdeflate read+copy CPU)")
        print(f"    CPU {r['cpu_s']:.2f} s = {r['cpu_s'] / c_read:.1f}x read+copy CPU{vs_fast}; "
              f"{real / r['cpu_s']:.1f}x real time by CPU; stages: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in r["timings"].items())
              + f"; peaks {r['counts']['peaks']}, points {r['counts']['points']}"
              + ("" if not before else f"; package {r['package']}"))
    if before:
        print(f"  cloud against BEFORE: {compare_clouds(clouds[0], clouds[-1])}")


def extract_commit(ref: str, d: Path) -> Path:
    """The package ``mems_stereo`` of git commit ``ref`` extracted under ``d``."""
    out = d / f"src-{ref}"
    if not out.exists():
        out.mkdir()
        tar = subprocess.run(["git", "archive", ref, "mems_stereo"], cwd=ROOT, check=True,
                             capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(out)], input=tar, check=True)
    return out


IMPORTS = r"""
import json, sys, time
out = {}
for mod in sys.argv[1:]:
    t = time.perf_counter()
    __import__(mod)
    out[mod] = time.perf_counter() - t
out["numba loaded"] = "numba" in sys.modules
print(json.dumps(out))
"""


def startup(d: Path) -> None:
    """Second run of ``mems-stereo process samples/room.h5`` (wall, CPU) and import times."""
    cli = [sys.executable, "-c", "import sys; from mems_stereo.cli import main; "
           "sys.exit(main(sys.argv[1:]))", "process", str(ROOT / "samples" / "room.h5"),
           "-o", str(d / "room.ply")]
    walls, cpus = [], []
    # a private table cache, filled by the first run: the shared one keeps 16 tables, and
    # other jobs' tests on this machine can evict the room's between two runs
    env = dict(os.environ, MEMS_STEREO_CACHE=str(d / "cache-startup"))
    for _ in range(6):  # the first fills numba's and the table's caches where empty
        t0 = time.perf_counter()
        c0 = os.times()
        subprocess.run(cli, check=True, capture_output=True, cwd=ROOT, env=env)
        c1 = os.times()
        walls.append(time.perf_counter() - t0)
        cpus.append((c1.children_user - c0.children_user) + (c1.children_system
                                                             - c0.children_system))
    r = measure_child(IMPORTS, "numpy", "mems_stereo", "mems_stereo.pipeline.run", "open3d")
    heavy = subprocess.run(
        [sys.executable, "-c", "import sys; from mems_stereo.cli import main; "
         "main(['-q'] + sys.argv[1:]); print(sorted(m for m in ('open3d', 'matplotlib', "
         "'numba', 'dask', 'scipy.stats') if m in sys.modules))", "process",
         str(ROOT / "samples" / "room.h5"), "-o", str(d / "room.ply")],
        check=True, capture_output=True, text=True, cwd=ROOT,
        env=env).stdout.strip().splitlines()[-1]
    best = min(walls[1:])
    print(f"startup: `mems-stereo process samples/room.h5 -o room.ply`, runs 2 to 6: "
          f"{', '.join(f'{w:.2f}' for w in walls[1:])} s wall (median "
          f"{float(np.median(walls[1:])):.2f} s), "
          f"{', '.join(f'{c:.2f}' for c in cpus[1:])} s CPU (user + system), "
          f"interpreter start included (target <= 1.5 s wall: "
          f"{'met' if best <= 1.5 else 'NOT met'}; load average {os.getloadavg()[0]:.1f}); "
          f"heavy modules it loads: {heavy}")
    print("  imports, one after the other in a fresh process: "
          + ", ".join(f"{k} {v:.2f} s" for k, v in r.items() if k not in ("maxrss_mb",
                                                                          "numba loaded"))
          + f"; numba loaded by these: {r['numba loaded']}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gigabytes", type=float, default=2.0)
    ap.add_argument("--dense-shots", type=int, nargs="*", default=[200_000, 2_000_000])
    ap.add_argument("--seed", type=int, default=14)
    ap.add_argument("--runs", nargs="+", choices=["cold", "warm"], default=["cold", "warm"],
                    help="process with the interval-table cache empty and/or filled")
    ap.add_argument("--dir", default=None, help="where to write the recording (default: a "
                                                 "temporary directory, removed afterwards)")
    ap.add_argument("--no-startup", action="store_true", help="skip the startup figures")
    ap.add_argument("--before", default=None, metavar="COMMIT",
                    help="also process each dense recording with the package of this git "
                         "commit (same recording, same table cache, same minutes)")
    args = ap.parse_args()
    if not args.no_startup:
        with tempfile.TemporaryDirectory(dir=args.dir) as d:
            startup(Path(d))
    if args.gigabytes > 0:
        stream(args)
    for i, n in enumerate(args.dense_shots):
        with tempfile.TemporaryDirectory(dir=args.dir) as d:
            dense(n, args.seed + i, Path(d), args.runs, args.before)


def stream(args):
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = Path(d) / "big.h5"
        t0 = time.perf_counter()
        n = make_recording(path, args.gigabytes)
        size = path.stat().st_size
        print(f"recording: {n} shots x 192 pixels, {size / 1e9:.2f} GB on disk, written in "
              f"{time.perf_counter() - t0:.1f} s")
        # a cold interval-table cache, as when this figure was first measured
        env = dict(os.environ, MEMS_STEREO_CACHE=str(Path(d) / "cache"))
        out = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True,
                             text=True, check=True, cwd=ROOT, env=env)
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
