"""Scale-out: process_split and process_many over 1, 2, 4, … workers against one process (issue 14).

Simulates (``benchmarks/_dense.py``, never the samples) one dense floodlight
recording of ``--shots`` shots for ``process_split`` and ``--recordings``
recordings of ``--many-shots`` shots each for ``process_many`` (6 MHz
background, the room scene, own seeds), processes them in this process
(``process_recording``, the reference and the 1-core time T1), then on a
``LocalCluster`` of each worker count in ``--workers`` (single-threaded
worker processes; default 1, 2, 4, … up to the machine's cores), and prints
per count the wall time, speed-up T1/Tn, efficiency speed-up/n, and whether
every result is identical to one process (histograms, cloud, counts).

What bounds the speed-up on any machine is printed too: the client's serial
seconds in ``process_split`` (its wall time less the time it waited on its
workers: the header, the table's scatter, the neighbour support of the
peak detector and the matched filter's confirmation — the detector's per-pixel
stages run in blocks of pixels on the workers —, joining the peak blocks' means)
and the bytes the client gathers, per part, against T1 and against one worker's
time; the serial fraction f = serial / T1 gives Amdahl's bound 1 / (f + (1 − f)/n)
for 16 workers.  On a machine shared with
other jobs wall times say little, so the CPU seconds of the same runs are
printed too: the client process (with a LocalCluster: its scheduler too) and
its calling thread, and each worker process (with its minor page faults),
against one process's CPU; and where one worker's extra wall time over one
process goes: the worker's CPU beyond one process's, the client's serial
work, and the rest (the client's round trips between the stages, transfers).

Every worker is warmed up first (compiled kernels loaded from numba's disk
cache), as on a long-lived cluster; cluster start-up is printed apart.  Every
timing is taken ``--repeats`` times (default 3) and the medians are compared:
on a shared VM one run's wall time varies by ±5 %.  The
interval table's rows come from a private disk cache filled before any timed
run (warm), so no timed run computes rows.
Open3D is not needed (the core never imports it).

Run:  .venv/bin/python benchmarks/bench_scale.py [--workers 1 2 4 8 16] [--shots 400000]
      [--recordings 8] [--many-shots 50000] [--repeats 3] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _dense import make_dense_recording  # noqa: E402

from mems_stereo.pipeline.distributed import dask_client, process_many, process_split  # noqa: E402
from mems_stereo.pipeline.run import process_recording  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def machine() -> str:
    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()}: {os.cpu_count()} logical cores, {cpu}, {platform.system()}"


def same(a, b) -> bool:
    ok = a.counts == b.counts and a.truth == b.truth
    for k in a.histograms:
        ok &= np.array_equal(a.histograms[k], b.histograms[k])
    ok &= np.array_equal(a.cloud.points, b.cloud.points, equal_nan=True)
    for k in a.cloud.attributes:
        ok &= np.array_equal(a.cloud[k], b.cloud[k], equal_nan=True)
    return bool(ok)


def _cpu_seconds() -> float:
    return _usage()[0]


def _usage() -> tuple[float, int]:
    """CPU seconds (user + system) and minor page faults of this process so far."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime, r.ru_minflt


def default_workers() -> list[int]:
    n, out = os.cpu_count() or 1, [1]
    while out[-1] * 2 <= n:
        out.append(out[-1] * 2)
    return out


def tile_recording(src, dst, n_copies: int, compression: str | None = "gzip") -> int:
    """Write ``n_copies`` of recording ``src`` end to end into ``dst``; returns the shots.

    Where Open3D (the simulator's ray caster) is missing, e.g. on a compute
    node, a simulated recording travels and is tiled there.  The tiles are a
    consistent recording only when ``src`` lasts a whole number of mirror
    periods (the trajectory repeats): that is checked.  Shot times and zero
    crossings move by the duration of ``src`` per copy; the bins repeat.
    """
    from mems_stereo.io.recording import RecordingWriter, read_recording

    rec = read_recording(src, truth=False)
    s = rec.system
    K = rec.bins.shape[0]
    duration = K / s.laser.f_rep
    periods = duration * s.scanner.f_mech
    if abs(periods - round(periods)) > 1e-6:
        raise SystemExit(f"{src}: {K} shots last {periods:.6f} mirror periods; tiling needs a "
                         "whole number")
    # one period's worth of crossings per copy: those in [0, T); the source's
    # crossings before 0 and from T on stay at the two ends
    z, r = rec.zero_crossings, np.asarray(rec.rising)
    mid = (z >= 0.0) & (z < duration)
    zc = np.concatenate([z[z < 0.0]] + [z[mid] + k * duration for k in range(n_copies)]
                        + [z[z >= duration] + (n_copies - 1) * duration])
    rising = np.concatenate([r[z < 0.0]] + [r[mid]] * n_copies + [r[z >= duration]])
    with RecordingWriter(dst, s, K * n_copies, zc, rising, compression=compression,
                         chunk_shots=1024) as w:
        for k in range(n_copies):
            w.append(rec.shot_time + k * duration, rec.bins)
    return K * n_copies


def _median(xs) -> float:
    return float(np.median(np.asarray(xs, dtype=np.float64)))


def _spread(xs) -> str:
    return ", ".join(f"{x:.2f}" for x in xs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=None,
                    help="worker counts (default: 1, 2, 4, ... up to the cores)")
    ap.add_argument("--shots", type=int, default=400_000,
                    help="shots of the recording split by process_split (default 400000)")
    ap.add_argument("--recordings", type=int, default=None,
                    help="recordings for process_many (default: 2 x the most workers, >= 4)")
    ap.add_argument("--many-shots", type=int, default=50_000,
                    help="shots per recording for process_many (default 50000)")
    ap.add_argument("--seed", type=int, default=20261123)
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed runs of each (one process, each worker count): medians are "
                         "compared (default 3)")
    ap.add_argument("--dir", default=None, help="where to write the recordings")
    ap.add_argument("--source", default=None,
                    help="tile this recording (a whole number of mirror periods long) instead "
                         "of simulating: --shots and --many-shots are rounded to whole copies "
                         "(for machines without Open3D)")
    args = ap.parse_args()
    workers = args.workers or default_workers()
    n_rec = args.recordings or max(4, 2 * max(workers))
    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        t0 = time.perf_counter()
        big = Path(d) / "split.h5"
        paths = [Path(d) / f"many{i}.h5" for i in range(n_rec)]
        if args.source is None:
            make_dense_recording(big, args.shots, args.seed)
            for i, p in enumerate(paths):
                make_dense_recording(p, args.many_shots, args.seed + 1 + i)
            how = "simulated"
        else:
            from mems_stereo.io.recording import read_header

            k_src = read_header(args.source).shape[0]
            args.shots = tile_recording(args.source, big, max(1, round(args.shots / k_src)))
            n_many = max(1, round(args.many_shots / k_src))
            for p in paths:
                args.many_shots = tile_recording(args.source, p, n_many)
            how = f"tiled from {args.source}"
        print(f"{how}: 1 x {args.shots} shots (split) and {n_rec} x {args.many_shots} shots "
              f"(many), 6 MHz floodlight, in {time.perf_counter() - t0:.0f} s")

        # a private, filled interval-table cache: the shared one (~/.cache/mems-stereo)
        # keeps 16 tables, and other jobs' tests can evict this one between the runs
        # (its rows then computed again inside a timed run); workers inherit it
        from mems_stereo.io.recording import read_system
        from mems_stereo.pipeline.intervals import IntervalTable
        from mems_stereo.pipeline.settings import Settings

        os.environ["MEMS_STEREO_CACHE"] = str(Path(d) / "cache")
        for p in (big, paths[0]):
            IntervalTable.for_settings(read_system(p), Settings()).fill_all().save_cache()
        process_recording(paths[0])  # warm up: compiled kernels from the disk cache
        R = max(1, args.repeats)
        runs = {"split": [], "split_cpu": [], "split_faults": [], "many": [], "many_cpu": []}
        for _ in range(R):  # every timing R times: the medians are compared (noisy VMs)
            t0 = time.perf_counter()
            c0 = time.process_time()
            f0 = _usage()[1]
            one_split = process_recording(big)
            runs["split"].append(time.perf_counter() - t0)
            runs["split_cpu"].append(time.process_time() - c0)
            runs["split_faults"].append(_usage()[1] - f0)
        for _ in range(R):
            t0 = time.perf_counter()
            c0 = time.process_time()
            one_many = [process_recording(p) for p in paths]
            runs["many"].append(time.perf_counter() - t0)
            runs["many_cpu"].append(time.process_time() - c0)
        t1_split, c1_split = _median(runs["split"]), _median(runs["split_cpu"])
        f1_split = int(_median(runs["split_faults"]))
        t1_many, c1_many = _median(runs["many"]), _median(runs["many_cpu"])
        rt_split = args.shots / 20e3
        print(f"one process (median of {R} runs): split recording {t1_split:.2f} s wall "
              f"({_spread(runs['split'])}), {c1_split:.2f} s CPU ({rt_split / t1_split:.1f}x real "
              f"time), {n_rec} recordings {t1_many:.2f} s ({_spread(runs['many'])})")

        rows = []
        for n in workers:
            t0 = time.perf_counter()
            with dask_client("local", n_workers=n) as client:
                t_start = time.perf_counter() - t0
                # warm up: a dense recording loads the compiled kernels (small ones do not)
                client.run(process_recording, str(paths[0]))
                ts_runs, tm_runs, ok_split, ok_many = [], [], True, True
                for _ in range(R):  # the CPU figures below are those of the last run
                    w0 = client.run(_usage)
                    t0 = time.perf_counter()
                    sp = process_split(big, scheduler=client)
                    ts_runs.append(time.perf_counter() - t0)
                    w1 = client.run(_usage)
                    sp.timings["worker_cpu"] = sorted(w1[k][0] - w0[k][0] for k in w0)
                    sp.timings["worker_faults"] = sorted(w1[k][1] - w0[k][1] for k in w0)
                    ok_split = ok_split and same(one_split, sp)
                for _ in range(R):
                    w0 = client.run(_cpu_seconds)
                    c0 = time.process_time()
                    t0 = time.perf_counter()
                    many = process_many(paths, scheduler=client)
                    tm_runs.append(time.perf_counter() - t0)
                    w1 = client.run(_cpu_seconds)
                    sp.timings["many_client_cpu"] = time.process_time() - c0
                    sp.timings["many_worker_cpu"] = sorted(w1[k] - w0[k] for k in w0)
                    ok_many = ok_many and all(same(a, b) for a, b in zip(one_many, many))
            sp.timings["split_runs"], sp.timings["many_runs"] = ts_runs, tm_runs
            rows.append((n, t_start, _median(ts_runs), ok_split, _median(tm_runs), ok_many,
                         sp.timings))

    print()
    print(f"(medians of {R} runs each, the runs in brackets; speed-ups are median against "
          f"median: over one process, and over one worker, as the issue states its targets)")
    print("| workers | process_split s | speed-up | efficiency | ÷ 1 worker | identical | "
          "process_many s | speed-up | efficiency | ÷ 1 worker | identical | cluster start s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    one_w = next((r for r in rows if r[0] == 1), None)
    for n, t_start, t_split, ok_s, t_many, ok_m, tm in rows:
        ws = "—" if one_w is None else f"{one_w[2] / t_split:.2f}x"
        wm = "—" if one_w is None else f"{one_w[4] / t_many:.2f}x"
        print(f"| {n} | {t_split:.2f} ({_spread(tm['split_runs'])}) | {t1_split / t_split:.2f}x | "
              f"{t1_split / t_split / n:.0%} | {ws} | {ok_s} | {t_many:.2f} "
              f"({_spread(tm['many_runs'])}) | {t1_many / t_many:.2f}x | "
              f"{t1_many / t_many / n:.0%} | {wm} | {ok_m} | {t_start:.1f} |")
    print()
    print("what bounds process_split (client side, per worker count):")
    t1w = next((r[2] for r in rows if r[0] == 1), None)
    for n, *_, tm in rows:
        if "client_serial" not in tm:  # an older pipeline without these figures
            print(f"  {n:>2} workers: stages " + ", ".join(f"{k} {v:.2f} s"
                                                      for k, v in tm.items()))
            continue
        f = tm["client_serial"] / t1_split
        amdahl16 = 1.0 / (f + (1.0 - f) / 16)
        mb = tm["client_bytes"] / 1e6
        vs1w = (f"; {tm['client_serial'] / t1w:.1%} of one worker's {t1w:.2f} s"
                if t1w else "")
        print(f"  {n:>2} workers: {int(tm['parts'])} shot parts, "
              f"{int(tm.get('peak_blocks', 0))} peak blocks fused on the workers; client "
              f"serial {tm['client_serial']:.2f} s (wall less {tm.get('client_wait', 0):.2f} s "
              f"waiting on the workers; header {tm['read_header']:.2f}, peak stage "
              f"{tm['peaks'] - tm.get('peaks_wait', 0.0):.2f} = {tm['peaks']:.2f} less "
              f"{tm.get('peaks_wait', 0.0):.2f} waiting on the workers' blocks of pixels "
              f"and candidate counts); gathered {mb:.1f} MB in all = {mb / tm['parts']:.2f} MB per "
              f"part; serial fraction {f:.1%} of one process's {t1_split:.2f} s{vs1w} -> "
              f"Amdahl bound on 16 workers {amdahl16:.1f}x")
    one = next((r for r in rows if r[0] == 1 and "worker_cpu" in r[6]), None)
    if one is not None:
        # where one worker's extra time over one process goes: its CPU beyond one
        # process's (the same stages, plus Dask's threads in the worker), the client's
        # serial work (the worker idles meanwhile), and the rest (round trips of the
        # tasks' results, transfers, the client process's threads competing for cores)
        tm = one[6]
        extra = one[2] - t1_split
        cpu_x = tm["worker_cpu"][0] - c1_split
        rest = extra - cpu_x - tm["client_serial"]
        print(f"one worker against one process: {one[2]:.2f} - {t1_split:.2f} = {extra:+.2f} s "
              f"= worker CPU beyond one process's {cpu_x:+.2f} s ({tm['worker_cpu'][0]:.2f} "
              f"against {c1_split:.2f} s; page faults {tm['worker_faults'][0]} against "
              f"{f1_split} in one process) + client serial {tm['client_serial']:.2f} s + the "
              f"rest {rest:+.2f} s (waiting between tasks: {int(tm.get('client_waits', 0))} "
              f"round trips of the client, the tasks' transfers, the client's threads on "
              f"the shared cores: {tm['client_cpu']:.2f} s of client CPU)")
    print(f"load average at the end: {os.getloadavg()[0]:.1f} (other jobs share these cores)")
    print()
    print("on a machine shared with other jobs the wall times above say little; the CPU "
          "seconds of the same runs (client process and each worker process) bound the "
          "speed-up with one core per process:")
    for n, *_, tm in rows:
        if "worker_cpu" not in tm:
            continue
        wc = tm["worker_cpu"]
        bound = c1_split / (tm["client_cpu"] + max(wc))
        main = tm.get("client_main_cpu", float("nan"))
        print(f"  {n:>2} workers: client {tm['client_cpu']:.2f} s CPU (its main thread "
              f"{main:.2f} s = {main / c1_split:.1%} of one process's CPU; the rest is the "
              f"in-process scheduler and Dask's communication threads), workers "
              f"{' / '.join(f'{x:.2f}' for x in wc)} s CPU (sum {sum(wc):.2f} s against "
              f"{c1_split:.2f} s in one process; minor page faults "
              f"{' / '.join(str(x) for x in tm.get('worker_faults', []))} against "
              f"{f1_split} in one process); one process's CPU / (client + busiest "
              f"worker) = {bound:.2f}x, / (client's main thread + busiest worker) = "
              f"{c1_split / (main + max(wc)):.2f}x; client CPU = "
              f"{tm['client_cpu'] / c1_split:.1%} of one process's")
        if "many_worker_cpu" in tm:
            mc = tm["many_worker_cpu"]
            print(f"      process_many: client {tm['many_client_cpu']:.2f} s CPU, workers "
                  f"{' / '.join(f'{x:.2f}' for x in mc)} s CPU (sum {sum(mc):.2f} s against "
                  f"{c1_many:.2f} s in one process); one process's CPU / busiest worker = "
                  f"{c1_many / max(mc):.2f}x")
    best_s = max(t1_split / r[2] for r in rows)
    best_m = max(t1_many / r[4] for r in rows)
    print(f"best speed-up: process_split {best_s:.2f}x, process_many {best_m:.2f}x on "
          f"{max(workers)} workers max; all identical: {all(r[3] and r[5] for r in rows)}")
    one_w = next((r for r in rows if r[0] == 1), None)
    if one_w is not None:  # the issue states its targets "over one worker"
        bw_s = max(one_w[2] / r[2] for r in rows)
        bw_m = max(one_w[4] / r[4] for r in rows)
        print(f"over one worker ({one_w[2]:.2f} s split, {one_w[4]:.2f} s many, medians): "
              f"process_split {bw_s:.2f}x, process_many {bw_m:.2f}x")
    # the targets, read off the figures above: over one worker as the issue
    # words them, and over one process (stricter: one worker carries Dask's overhead)
    cores = os.cpu_count() or 1
    want_s = 10.0 if max(workers) >= 16 else 1.8
    want_m = 12.0 if max(workers) >= 16 else 1.8

    def verdict(x, want):
        return f"{'met' if x >= want else 'NOT met'} ({x:.2f}x)"

    over = [("one process", best_s, best_m)]
    if one_w is not None:
        over.insert(0, ("one worker", bw_s, bw_m))
    for name, xs, xm in over:
        print(f"targets (issue 14; this machine has {cores} cores, so {max(workers)} workers "
              f"at most), over {name}: process_split >= {want_s:g}x by wall: "
              f"{verdict(xs, want_s)}; process_many >= {want_m:g}x: {verdict(xm, want_m)}")
    for n, *_, tm in rows:
        if "client_serial" in tm:
            f = tm["client_serial"] / t1_split
            print(f"  {n:>2} workers: serial fraction {f:.1%} (target <= 5 %: "
                  f"{'met' if f <= 0.05 else 'NOT met'}) -> Amdahl bound on 16 workers "
                  f"{1.0 / (f + (1.0 - f) / 16):.1f}x (target >= 10x)")


if __name__ == "__main__":
    main()
