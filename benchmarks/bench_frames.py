"""Live frames (issue 31): per-frame latency, throughput, drops and memory of a live replay.

For each recording (``room``: room light, 100 kHz background per pixel; ``flood``: dense
floodlight, 6 MHz per pixel: nearly every pixel-slot holds a detection), each frame rate
(--frame-rates, default 10 20 50 Hz) and each replay rate (--rates, default 1 and max) a
fresh process runs what ``mems-stereo live --replay REC --rate R --frame-rate HZ -o DIR/``
runs: the replay source in its own thread, the frame-bounded queue (3 frames), the
FrameProcessor (warmed up on a synthetic frame before the clock starts) and the folder
sink writing one PLY per frame.  Printed per run: frames written and dropped, the latency
of each written frame (wall time when its cloud was written minus the time its end was
due on the recording's clock, replayed; at ``max``: minus when its last shot arrived),
median / p99 / max, against the targets (median <= 1 frame period, p99 <= 2, no drop at
rate 1), throughput (frames and recording seconds per wall second), CPU seconds per wall
second (how much of the cores the threads and the frame worker processes use), and the
resident memory (VmRSS of the process and its workers) sampled every 0.5 s: its peak in
the first and in the last quarter of the run (flat: the
same) and ru_maxrss.

The recordings are SIMULATED (``benchmarks/_dense.py``, the room scene, seeds 7 and 8)
with --seconds of shots (default 2 s = 40,000 shots) and cached in --dir; a replay at
rate 1 loops the recording for --minutes (default 0: one pass), each pass shifted by a
whole number of mechanical periods so the scan goes on.

``--workers 1 2`` (the default) runs this checkout's package with each number of frame
worker processes (:mod:`mems_stereo.pipeline.frame_workers`; 1: the frames in the one
process, as ``live --workers 1``), alternating; the lines are marked ``w=N``.

With ``--base-src DIR`` (a checkout of another commit, e.g. ``git worktree add /tmp/base
REV``) every configuration also runs that commit's package (its ``mems_stereo``, ``viz`` and
``calib`` folders ahead of the editable install, one process), marked ``base``, and a
last table gives the CPU s per frame of each run against it (CPU time of all the
processes: on a shared machine the wall-clock figures
follow the load, printed with each run).

Run:  nice .venv/bin/python benchmarks/bench_frames.py [--recordings room flood]
      [--frame-rates 10 20 50] [--rates 1 max] [--seconds 2] [--minutes 0] [--dir /tmp/bf]
      [--base-src DIR] [--no-temporal] [--workers 1 2]
The log goes to benchmarks/results/bench_frames_<UTC time>.log.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
SEEDS = {"room": (7, 1e5), "flood": (8, 6e6)}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} cores)"
    except OSError:
        pass
    return f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"


def vm_rss_mb(pid="self") -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:  # a worker that ended
        return 0.0
    return float("nan")


def cpu_seconds(pids) -> float:
    """User + system CPU s of the processes ``pids`` so far (/proc/PID/stat)."""
    tick, total = os.sysconf("SC_CLK_TCK"), 0.0
    for pid in pids:
        try:
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(f[11]) + int(f[12])) / tick
    return total


def tree_rss_mb(pids) -> float:
    """VmRSS of this process plus its worker processes ``pids``, MB."""
    return vm_rss_mb() + sum(vm_rss_mb(p) for p in pids)


# ------------------------------------------------------------------ the child run

def looped_source(path: str, rate, seconds: float):
    """A ReplaySource that replays ``path`` for ``seconds`` of recording time (at least one
    pass), each pass shifted by a whole number of mechanical periods."""
    from mems_stereo.io.live_sources import PIECE_SECONDS, ReplaySource

    class Looped(ReplaySource):
        def chunks(self):
            t = self.t_first
            rec_s = float(self.zero_crossings[-1] - t)
            period = math.ceil(rec_s * self.system.scanner.f_mech) / self.system.scanner.f_mech
            loops = max(1, math.ceil(seconds / period))
            self.wall0 = time.monotonic()
            last_z = -np.inf
            for k in range(loops):
                for c in ReplaySource(self.path, None, chunk_shots=2048).chunks():
                    ts, zc = c.shot_time + k * period, c.zero_crossings + k * period
                    keep = zc > last_z + 1e-6
                    zc, ri = zc[keep], c.rising[keep]
                    if zc.size:
                        last_z = float(zc[-1])
                    step = max(1, int(PIECE_SECONDS * self.system.laser.f_rep))
                    for a in range(0, ts.size, step if self.rate else ts.size):
                        s = slice(a, a + (step if self.rate else ts.size))
                        due = self.due(float(ts[s][-1]))
                        if due is not None and self._stop.wait(max(0.0, due - time.monotonic())):
                            self.ended = "stopped"
                            return
                        yield self.chunk(ts[s], c.bins[s], zc, ri)
            self.ended = "finished"

    return Looped(path, rate)


def use_package(src: str) -> None:
    """Import ``mems_stereo`` (with its ``viz`` and ``calib`` folders) from the checkout
    ``src`` instead of the editable install."""
    sys.meta_path[:] = [f for f in sys.meta_path
                        if "__editable__" not in getattr(f, "__module__", "")]
    sys.path.insert(0, src)
    import mems_stereo

    mems_stereo.__path__.append(src)  # viz/ and calib/ are top-level folders there
    if not mems_stereo.__file__.startswith(src):
        raise SystemExit(f"--base-src: mems_stereo imported from {mems_stereo.__file__}")


def processor(system, hz: float, fusion: bool, workers: int):
    """``(processor, warm-up s)``: ``workers`` processes where this checkout has them."""
    from mems_stereo.pipeline.frames import FrameProcessor
    from mems_stereo.pipeline.live_warmup import warm_up

    try:
        from mems_stereo.pipeline.frame_workers import frame_processor
    except ImportError:  # a checkout before frame workers: one process
        proc = FrameProcessor(system, frame_rate=hz, fusion=fusion)
    else:
        proc = frame_processor(system, workers=workers, frame_rate=hz, fusion=fusion)
    return proc, (proc.warm_up if getattr(proc, "workers", 0) else warm_up(proc))


def child(path: str, hz: float, rate, seconds: float, fusion: bool = True,
          workers: int = 1) -> dict:
    if os.environ.get("BENCH_PACKAGE_SRC"):
        use_package(os.environ["BENCH_PACKAGE_SRC"])

    from mems_stereo.viz.export_frames import FrameFolderSink

    from mems_stereo.pipeline.live_queue import LiveRun

    src = looped_source(path, rate, seconds)
    proc, warm = processor(src.system, hz, fusion, workers)
    pids = list(getattr(proc, "worker_pids", []))
    rss, done = [], threading.Event()

    def sample():
        t0 = time.monotonic()
        while not done.wait(0.5):
            rss.append((time.monotonic() - t0, tree_rss_mb(pids)))

    threading.Thread(target=sample, daemon=True).start()
    c0, w0 = time.process_time(), cpu_seconds(pids)
    with tempfile.TemporaryDirectory() as d:
        sink = FrameFolderSink(d, "bench")
        st = LiveRun(src, proc, sink.write, max_queued=3).run()
    done.set()
    cpu = time.process_time() - c0 + cpu_seconds(pids) - w0
    getattr(proc, "close", lambda: None)()
    r = np.array([v for _, v in rss]) if rss else np.array([vm_rss_mb()])
    q = max(1, r.size // 4)
    lat = np.asarray(st.latency) * 1e3
    return {"written": st.frames_written, "dropped": st.frames_dropped, "shots": st.shots,
            "shots_dropped": st.shots_dropped, "wall": st.wall, "cpu": cpu, "warm_up": warm,
            "lat_median": float(np.median(lat)) if lat.size else None,
            "lat_p99": float(np.percentile(lat, 99)) if lat.size else None,
            "lat_max": float(lat.max()) if lat.size else None,
            "rss_first": float(r[:q].max()), "rss_last": float(r[-q:].max()),
            "rss_max": float(r.max()), "samples": int(r.size), "workers": len(pids),
            "maxrss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


# ------------------------------------------------------------------ the parent

def recording(name: str, seconds: float, d: Path) -> Path:
    from _dense import make_dense_recording

    seed, bg = SEEDS[name]
    n = int(round(seconds * 20000))
    path = d / f"{name}_{n}.h5"
    if not path.exists():
        t0 = time.perf_counter()
        info = make_dense_recording(path, n, seed, background_hz=bg)
        print(f"simulated {path.name}: {n} shots, {bg / 1e6:g} MHz background, seed {seed}, "
              f"{info['bytes_on_disk'] / 1e6:.0f} MB ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    return path


def line(name: str, hz: float, rate, r: dict, rec_seconds: float) -> str:
    period = 1e3 / hz
    ok = (r["lat_median"] is not None and r["lat_median"] <= period
          and r["lat_p99"] <= 2 * period and (rate is None or r["dropped"] == 0))
    lat = ("no frame written" if r["lat_median"] is None else
           f"latency median {r['lat_median']:.0f} / p99 {r['lat_p99']:.0f} / max "
           f"{r['lat_max']:.0f} ms (period {period:.0f} ms)")
    rt = "max" if rate is None else f"{rate:g}"
    return (f"  {name:5s} {hz:4g} Hz {r.get('workers', 0)} workers rate {rt:>3s}: "
            f"{r['written']} written, {r['dropped']} dropped; {lat}; "
            f"{r['written'] / r['wall']:.2f} frames/s, {rec_seconds / r['wall']:.2f}x real "
            f"time; CPU {r['cpu'] / r['wall']:.2f} cores, "
            f"{r['cpu'] / max(r['written'], 1):.2f} CPU s per frame written; RSS first/last "
            f"quarter {r['rss_first']:.0f}/{r['rss_last']:.0f} MB (max {r['maxrss']:.0f}); warm-up "
            f"{r['warm_up']:.1f} s; targets {'met' if ok else 'NOT met'}")


def run_child(path: Path, hz: float, rtext: str, secs: float, src: str | None,
              fusion: bool = True, workers: int = 1) -> dict:
    """One run in a fresh process (``src``: another checkout's package); its result with
    the load average at its start, or ``{"failed": the end of its stderr}``."""
    env = dict(os.environ)
    env.pop("BENCH_PACKAGE_SRC", None)
    if src:
        env["BENCH_PACKAGE_SRC"] = src
    load = os.getloadavg()[0]
    p = subprocess.run([sys.executable, __file__, "--child", str(path), str(hz), rtext,
                        str(secs), "1" if fusion else "0", str(workers)],
                       capture_output=True, text=True,
                       env=env)
    if p.returncode:
        return {"failed": p.stderr[-400:]}
    return {**json.loads(p.stdout.strip().splitlines()[-1]), "load": load}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", nargs="+", default=["room", "flood"], choices=list(SEEDS))
    ap.add_argument("--frame-rates", nargs="+", type=float, default=[10.0, 20.0, 50.0])
    ap.add_argument("--rates", nargs="+", default=["1", "max"])
    ap.add_argument("--seconds", type=float, default=2.0, help="recording length, s")
    ap.add_argument("--minutes", type=float, default=0.0,
                    help="replay at rate 1 loops the recording this long (0: one pass)")
    ap.add_argument("--dir", default=None)
    ap.add_argument("--base-src", default=None,
                    help="a checkout of another commit: each run alternates it and this one")
    ap.add_argument("--no-temporal", action="store_true",
                    help="frames without the temporal fusion (the frame stages alone)")
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2],
                    help="frame worker processes of this checkout's runs (1: one process; "
                         "each value a run of its own)")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        path, hz, rate, seconds, fusion, workers = a.child
        print(json.dumps(child(path, float(hz), None if rate == "max" else float(rate),
                               float(seconds), fusion == "1", int(workers))))
        return 0
    d = Path(a.dir or tempfile.mkdtemp(prefix="bench_frames_"))
    d.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d_%H%M%S", time.gmtime())
    log = ROOT / "results" / f"bench_frames_{stamp}.log"
    out = [f"bench_frames {stamp} UTC; CPU {cpu_model()}; load average "
           f"{os.getloadavg()[0]:.1f}; argv {' '.join(sys.argv[1:])}"]
    print(out[0], flush=True)
    versions = [(f"w={n}", None, n) for n in a.workers]
    if a.base_src:
        versions.insert(0, ("base", os.path.abspath(a.base_src), 1))
    per_frame = []
    for name in a.recordings:
        path = recording(name, a.seconds, d)
        for hz in a.frame_rates:
            for rtext in a.rates:
                rate = None if rtext == "max" else float(rtext)
                secs = a.minutes * 60 if (rate is not None and a.minutes) else 0.0
                cpu = {}
                for tag, src, workers in versions:
                    r = run_child(path, hz, rtext, secs, src, not a.no_temporal, workers)
                    if "failed" in r:
                        out.append(f"  {tag:4s} {name} {hz:g} Hz rate {rtext}: FAILED "
                                   f"{r['failed']}")
                    else:
                        out.append(f"{tag:4s}" + line(name, hz, rate, r, max(secs, a.seconds))
                                   + f"; load {r['load']:.1f}")
                        cpu[tag] = r["cpu"] / max(r["written"], 1)
                    print(out[-1], flush=True)
                if "base" in cpu:
                    per_frame += [f"  {name:5s} {hz:4g} Hz rate {rtext:>3s} {t}: "
                                  f"{cpu['base']:.3f} -> {c:.3f} CPU s per frame "
                                  f"({cpu['base'] / c:.2f}x)" for t, c in cpu.items()
                                  if t != "base"]
    if per_frame:
        out += ["CPU s per frame written, base -> this checkout with w workers (speed-up):"] \
            + per_frame
        print("\n".join(out[-len(per_frame) - 1:]))
    log.parent.mkdir(exist_ok=True)
    log.write_text("\n".join(out) + "\n")
    print(f"log: {log}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
