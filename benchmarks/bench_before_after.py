"""Throughput of this checkout against another commit, in one run: dense ``process`` and
``process_split`` on a 2-worker LocalCluster.

One dense 6 MHz floodlight recording (``benchmarks/_dense.py``, ``--shots`` shots) is
processed by each package in turn, in fresh interpreters: ``process_recording`` (one
process, warm: the interval table's disk cache and the numba cache filled by an untimed
run first) and ``process_split`` over a ``LocalCluster`` of ``--workers`` single-threaded
workers (cluster started and warmed before the timed runs).  The other commit's package
is extracted with ``git archive`` and put first on ``PYTHONPATH`` (so the Dask workers
import it too).  Runs alternate between the two packages, ``--repeats`` times each;
medians are compared, every run is printed, and the clouds are checked identical.

Run:  .venv/bin/python benchmarks/bench_before_after.py --before COMMIT [--shots 200000]
      [--repeats 5] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _dense import make_dense_recording  # noqa: E402
from bench_scale import machine  # noqa: E402
from readme_figures_vs import extract_commit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import hashlib, json, sys, time
import mems_stereo as ms
path, mode, n, workers = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
def digest(res):
    return hashlib.sha256(res.cloud.to_structured().tobytes()).hexdigest()[:16]
times = []
if mode == "process":
    res = ms.process_recording(path)
    for _ in range(n):
        t = time.perf_counter(); res = ms.process_recording(path)
        times.append(time.perf_counter() - t)
else:
    try:
        from mems_stereo.pipeline.distributed import dask_client, process_split
    except ImportError:
        from mems_stereo.pipeline.split import dask_client, process_split
    with dask_client("local", n_workers=workers) as client:
        res = process_split(path, scheduler=client)
        for _ in range(n):
            t = time.perf_counter(); res = process_split(path, scheduler=client)
            times.append(time.perf_counter() - t)
print(json.dumps({"times": times, "digest": digest(res),
                  "package": ms.__file__}))
"""


def run_child(path: Path, mode: str, n: int, workers: int, src: Path | None) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src) + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", CHILD, str(path), mode, str(n), str(workers)],
                         capture_output=True, text=True, cwd=ROOT, env=env)
    if out.returncode != 0:
        raise SystemExit(f"{mode} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, metavar="COMMIT")
    ap.add_argument("--shots", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=14)
    args = ap.parse_args()
    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        rec = d / "dense.h5"
        make_dense_recording(rec, args.shots, args.seed)
        src = extract_commit(args.before, d)
        variants = [(f"before ({args.before})", src), ("this checkout", None)]
        res: dict = {(m, v): {"times": []} for m in ("process", "split") for v, _ in variants}
        for mode in ("process", "split"):
            for rep in range(args.repeats):
                for name, s in (variants if rep % 2 == 0 else variants[::-1]):
                    r = run_child(rec, mode, 1, args.workers, s)
                    res[(mode, name)]["times"] += r["times"]
                    res[(mode, name)]["digest"] = r["digest"]
                    print(f"{mode:8s} {name:22s} run {rep + 1}: {r['times'][0]:.3f} s "
                          f"(cloud {r['digest']})", flush=True)
        print(f"\n| {args.shots:,} dense shots | before s (median) | now s (median) | "
              "now / before | clouds identical |\n| --- | --- | --- | --- | --- |")
        ok = True
        for mode, label in (("process", "process_recording, one process"),
                            ("split", f"process_split, {args.workers} workers")):
            b = res[(mode, variants[0][0])]
            n = res[(mode, variants[1][0])]
            mb, mn = float(np.median(b["times"])), float(np.median(n["times"]))
            same = b["digest"] == n["digest"]
            ok &= same
            print(f"| {label} | {mb:.3f} | {mn:.3f} | {mn / mb:.3f} | {same} |")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
