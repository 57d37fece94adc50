"""Scale-out on Dask: 8 recordings on a 2-worker LocalCluster against one process (issue 7).

Simulates 8 room-light recordings (one second of the paper's system each,
20,000 shots x 192 pixels, different seeds), processes them one after the
other in this process, then with ``mems_stereo.pipeline.distributed.process_many`` on a
``LocalCluster(n_workers=2, threads_per_worker=1)``, checks the results are
identical, and prints both wall times and the speed-up (with and without the
cluster's start-up).  On a 2-core machine the ideal speed-up is 2.

Run:  .venv/bin/python benchmarks/bench_dask.py [--recordings 8] [--shots 20000]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

from mems_stereo.model.system import burkard2022
from mems_stereo.pipeline.distributed import dask_client, process_many
from mems_stereo.pipeline.run import process_recording
from mems_stereo.sim import load_scene, simulate, write_simulation

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=8)
    ap.add_argument("--shots", type=int, default=20000)
    args = ap.parse_args()
    s = burkard2022()
    scene = load_scene(ROOT / "samples" / "room_scene.json")
    with tempfile.TemporaryDirectory() as d:
        paths = []
        t0 = time.perf_counter()
        for i in range(args.recordings):
            rec = simulate(s, scene, args.shots, rng=np.random.default_rng(100 + i),
                           background_hz=1e5)
            p = Path(d) / f"rec{i}.h5"
            write_simulation(p, rec)
            paths.append(p)
        print(f"{args.recordings} recordings of {args.shots} shots x 192 pixels simulated in "
              f"{time.perf_counter() - t0:.1f} s")

        process_recording(paths[0])  # warm up: numba compile, interval table
        t0 = time.perf_counter()
        one = [process_recording(p) for p in paths]
        t_one = time.perf_counter() - t0

        t0 = time.perf_counter()
        with dask_client("local", n_workers=2) as client:
            t_start = time.perf_counter() - t0
            # warm up every worker the same way (compiled kernels, tables)
            client.run(process_recording, str(paths[0]))
            t1 = time.perf_counter()
            many = process_many(paths, scheduler=client)
            t_many = time.perf_counter() - t1
        t_many_total = t_many + t_start
        same = all(np.array_equal(a.cloud.points, b.cloud.points) and a.counts == b.counts
                   for a, b in zip(one, many))
        slots = args.recordings * args.shots * 192
        print(f"one process        : {t_one:6.2f} s ({slots / t_one / 1e6:.1f} M slots/s)")
        print(f"2-worker LocalCluster: {t_many:6.2f} s ({slots / t_many / 1e6:.1f} M slots/s); "
              f"cluster start-up {t_start:.1f} s")
        print(f"speed-up {t_one / t_many:.2f}x (warm workers), {t_one / t_many_total:.2f}x "
              f"including start-up; results identical: {same}")


if __name__ == "__main__":
    main()
