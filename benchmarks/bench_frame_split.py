"""One frame on several cores (issue 31): latency of live replays, one process against
frame-per-worker and each frame split across the workers.

For each recording (``room``: room light; ``flood``: dense floodlight, 6 MHz per pixel;
the simulated recordings of ``bench_frames.py``, cached in --dir), frame rate and replay
rate, a fresh process runs what ``mems-stereo live --replay REC --rate R --frame-rate HZ
-o DIR/`` runs (``bench_frames.child``: the looped replay source, the bounded queue of 3
frames, the folder sink), with each --modes:

* ``one`` — the frames in one process (``--workers 1``);
* ``frames`` — two worker processes, frame i in worker i mod 2 (``--split frames``);
* ``pixels`` — two worker processes, every frame's pixels and peaks split across both
  (``--split pixels``, :mod:`mems_stereo.pipeline.frame_split`);
* ``base`` (with --base-src DIR, a ``git archive`` of another commit) — that commit's
  package, one process.

The modes of one configuration run one after another, alternating, --repeat times.  Per
run: frames written and dropped, latency median / p99 / max against the targets (median
<= 1 period, p99 <= 2, no drop at rate 1), frames written per wall second, CPU s per
frame of all the processes, and for
``pixels`` each worker's CPU s per frame in each of the three steps and the main
process's CPU s per frame in the joins between them (wall-clock latency follows the load
of the shared machine: the load average is printed at each run's start and end; the CPU
figures do not depend on it).

Run:  nice .venv/bin/python benchmarks/bench_frame_split.py [--recordings room flood]
      [--frame-rates 10 20] [--rates 1] [--seconds 1] [--minutes 0.25] [--dir /tmp/bf]
      [--modes one frames pixels] [--base-src DIR] [--repeat 1]
The log goes to benchmarks/results/bench_frame_split_<UTC time>.log.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

import bench_frames  # noqa: E402  (the same folder: its child run and recordings)

#: mode -> (worker processes, split)
MODES = {"one": (1, "frames"), "frames": (2, "frames"), "pixels": (2, "pixels"),
         "base": (1, "frames")}
_made = []  # the processor of a child run (its figures are read after the run)


def _processor(split: str):
    """``bench_frames.processor`` with the split ``split`` (this checkout's package)."""

    def processor(system, hz: float, fusion: bool, workers: int):
        from mems_stereo.pipeline.frame_workers import frame_processor
        from mems_stereo.pipeline.live_warmup import warm_up

        proc = frame_processor(system, workers=workers, split=split, frame_rate=hz,
                               fusion=fusion)
        _made.append(proc)
        return proc, (proc.warm_up if proc.workers else warm_up(proc))

    return processor


def child(path: str, hz: float, rate, seconds: float, mode: str) -> dict:
    """One run in this process: ``bench_frames.child`` with the mode's processor."""
    workers, split = MODES[mode]
    if mode != "base":
        bench_frames.processor = _processor(split)
    r = bench_frames.child(path, hz, rate, seconds, True, workers)
    proc = _made[0] if _made else None
    n = max(r["written"], 1)
    if proc is not None and hasattr(proc, "step_cpu"):
        r["step_cpu"] = (proc.step_cpu / n).tolist()  # (3 steps, workers) CPU s per frame
        r["join_cpu"] = proc.join_cpu / n
    return r


def run_child(path: Path, hz: float, rtext: str, secs: float, mode: str,
              base_src: str | None) -> dict:
    env = dict(os.environ)
    env.pop("BENCH_PACKAGE_SRC", None)
    if mode == "base":
        env["BENCH_PACKAGE_SRC"] = base_src
    load0 = os.getloadavg()[0]
    p = subprocess.run([sys.executable, __file__, "--child", str(path), str(hz), rtext,
                        str(secs), mode], capture_output=True, text=True, env=env)
    if p.returncode:
        return {"failed": p.stderr[-400:]}
    return {**json.loads(p.stdout.strip().splitlines()[-1]), "load": (load0,
                                                                     os.getloadavg()[0])}


def line(name: str, hz: float, rtext: str, mode: str, r: dict) -> str:
    if "failed" in r:
        return f"  {mode:6s} {name:5s} {hz:4g} Hz rate {rtext}: FAILED {r['failed']}"
    period = 1e3 / hz
    med, p99 = r["lat_median"], r["lat_p99"]
    ok = (med is not None and med <= period and p99 <= 2 * period
          and (rtext == "max" or r["dropped"] == 0))
    lat = ("no frame written" if med is None else
           f"latency median {med:.0f} / p99 {p99:.0f} / max {r['lat_max']:.0f} ms")
    out = (f"  {mode:6s} {name:5s} {hz:4g} Hz rate {rtext:>3s}: {r['written']} written, "
           f"{r['dropped']} dropped; {lat} (period {period:.0f} ms); "
           f"{r['written'] / r['wall']:.2f} frames per wall s; "
           f"{r['cpu'] / max(r['written'], 1):.3f} CPU s per frame; targets "
           f"{'met' if ok else 'NOT met'}; load {r['load'][0]:.1f} -> {r['load'][1]:.1f}")
    if "step_cpu" in r:
        steps = " / ".join(",".join(f"{c * 1e3:.0f}" for c in col)
                           for col in zip(*r["step_cpu"]))
        per_worker = [sum(col) * 1e3 for col in zip(*r["step_cpu"])]
        out += (f"\n         workers' CPU ms per frame {', '.join(f'{c:.0f}' for c in per_worker)}"
                f" (steps scores,peaks,means: {steps}); joins {r['join_cpu'] * 1e3:.1f} ms")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", nargs="+", default=["room", "flood"],
                    choices=list(bench_frames.SEEDS))
    ap.add_argument("--frame-rates", nargs="+", type=float, default=[10.0, 20.0])
    ap.add_argument("--rates", nargs="+", default=["1"])
    ap.add_argument("--seconds", type=float, default=1.0, help="recording length, s")
    ap.add_argument("--minutes", type=float, default=0.25,
                    help="a replay at rate 1 loops the recording this long")
    ap.add_argument("--dir", default=None)
    ap.add_argument("--modes", nargs="+", default=["one", "frames", "pixels"],
                    choices=list(MODES))
    ap.add_argument("--base-src", default=None)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        path, hz, rate, seconds, mode = a.child
        if mode == "base":
            bench_frames.use_package(os.environ["BENCH_PACKAGE_SRC"])
        print(json.dumps(child(path, float(hz), None if rate == "max" else float(rate),
                               float(seconds), mode)))
        return 0
    modes = list(a.modes) + (["base"] if a.base_src and "base" not in a.modes else [])
    if "base" in modes and not a.base_src:
        ap.error("--modes base needs --base-src DIR")
    d = Path(a.dir or tempfile.mkdtemp(prefix="bench_frames_"))
    d.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d_%H%M%S", time.gmtime())
    log = ROOT / "results" / f"bench_frame_split_{stamp}.log"
    out = [f"bench_frame_split {stamp} UTC; CPU {bench_frames.cpu_model()}; load average "
           f"{os.getloadavg()[0]:.1f}; argv {' '.join(sys.argv[1:])}"]
    print(out[0], flush=True)
    for name in a.recordings:
        path = bench_frames.recording(name, a.seconds, d)
        for hz in a.frame_rates:
            for rtext in a.rates:
                secs = a.minutes * 60 if rtext != "max" else 0.0
                for _ in range(a.repeat):
                    for mode in modes:
                        r = run_child(path, hz, rtext, secs, mode, a.base_src)
                        out.append(line(name, hz, rtext, mode, r))
                        print(out[-1], flush=True)
    log.parent.mkdir(exist_ok=True)
    log.write_text("\n".join(out) + "\n")
    print(f"log: {log}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
