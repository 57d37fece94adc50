"""Dense recordings for the throughput benchmarks, and a measuring child process.

:func:`make_dense_recording` simulates (``mems_stereo.sim.simulate``, never the
samples' files) a floodlight recording of any length: the paper's system, the
room scene, 6 MHz background per pixel (nearly every pixel-slot holds a
detection), one continuous scan trajectory with a random phase, written in
segments of shots with :class:`~mems_stereo.io.recording.RecordingWriter`
(gzip, chunks of 1024 shots as the simulator's files; no ``/truth``, like a
real recording), so memory stays bounded whatever the length.

:func:`measure_child` runs a snippet in a fresh interpreter and returns the
JSON it prints plus its peak resident memory (``ru_maxrss`` of the child,
from ``resource.getrusage(RUSAGE_CHILDREN)`` in a wrapper process).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: the first lines of a child snippet that imports another commit's package: the
#: folder in ``BENCH_PACKAGE_SRC`` (a ``git archive`` of ``mems_stereo``) ahead of the
#: editable install's finder
PACKAGE_PRELUDE = r"""
import json, os, sys, time
src = os.environ.get("BENCH_PACKAGE_SRC")
if src:  # another commit's package: ahead of the editable install's finder
    sys.meta_path[:] = [f for f in sys.meta_path
                        if "__editable__" not in getattr(f, "__module__", "")]
    sys.path.insert(0, src)
"""
SEGMENT = 50_000  # shots simulated at a time


def make_dense_recording(path, n_shots: int, seed: int, background_hz: float = 6e6,
                         scene: str = "room_scene.json", compression: str | None = "gzip") -> dict:
    """Simulate a dense recording of ``n_shots`` shots into ``path``; returns its facts."""
    from mems_stereo.io.recording import RecordingWriter
    from mems_stereo.model.system import burkard2022
    from mems_stereo.sim import SimulationOptions, load_scene, simulate
    from mems_stereo.sim.trajectory import Trajectory, monitor_zero_crossings

    s = burkard2022()
    sc = load_scene(ROOT / "samples" / scene)
    rng = np.random.default_rng(seed)
    phase = float(rng.uniform(0.0, 2.0 * math.pi))
    traj = Trajectory.from_scanner(s.scanner, phase, 0.0, 0.0)
    times = np.arange(n_shots, dtype=np.float64) / s.laser.f_rep
    zc, rising = monitor_zero_crossings(traj, times, rng, 20e-9)
    with RecordingWriter(path, s, n_shots, zc, rising, compression=compression,
                         chunk_shots=1024) as w:
        for a in range(0, n_shots, SEGMENT):
            b = min(n_shots, a + SEGMENT)
            t0 = a / s.laser.f_rep
            rec = simulate(s, sc, b - a, rng=np.random.default_rng([seed, a]),
                           background_hz=background_hz,
                           options=SimulationOptions(start_time=t0,
                                                     phase=float(traj.monitor_phase(t0)),
                                                     drift=0.0))
            w.append(times[a:b], rec.bins)
    return {"shots": n_shots, "pixels": s.receiver.width * s.receiver.height,
            "f_rep": s.laser.f_rep, "bytes_on_disk": Path(path).stat().st_size,
            "bins_bytes": n_shots * s.receiver.width * s.receiver.height * 2}


WRAPPER = r"""
import json, resource, subprocess, sys
p = subprocess.run(sys.argv[1:], capture_output=True, text=True)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": p.returncode, "stdout": p.stdout, "stderr": p.stderr[-4000:],
                  "maxrss_mb": ru.ru_maxrss / 1024}))
"""


def measure_child(code: str, *args, env=None) -> dict:
    """Run ``python -c code *args`` in a fresh process; its last stdout line is JSON.

    Returns that JSON with ``maxrss_mb`` (the child's peak resident memory, MB)
    added.  Raises RuntimeError with the child's stderr when it fails.
    """
    cmd = [sys.executable, "-c", WRAPPER, sys.executable, "-c", code, *map(str, args)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=ROOT, env=env)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    if r["rc"] != 0:
        raise RuntimeError(f"child failed (rc {r['rc']}): {r['stderr']}")
    res = json.loads(r["stdout"].strip().splitlines()[-1])
    res["maxrss_mb"] = r["maxrss_mb"]
    return res


READ_COPY = r"""
import json, sys, time
t0 = time.perf_counter()
import h5py, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    ds = f["/shots/bins"]
    n = ds.shape[0]
    buf = None
    fast = None
    if sys.argv[2:] == ["libdeflate"]:  # the package's own reader of gzip'd chunks
        from mems_stereo.io.deflate_chunks import chunk_reader
        fast = chunk_reader(ds)
        if fast is None:
            raise SystemExit("no libdeflate reader for this file")
    t1 = time.perf_counter()
    c1 = time.process_time()
    for a in range(0, n, 8192):
        blk = ds[a:a + 8192] if fast is None else fast.read(a, min(n, a + 8192))
        if buf is None or buf.shape != blk.shape:
            buf = np.empty_like(blk)
        np.copyto(buf, blk)
    dt = time.perf_counter() - t1
print(json.dumps({"seconds": dt, "cpu_s": time.process_time() - c1}))
"""

PROCESS = r"""
import json, sys, time
t0 = time.perf_counter()
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings
t1 = time.perf_counter()
c1 = time.process_time()
res = process_recording(sys.argv[1])
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "seconds": t2 - t1, "cpu_s": time.process_time() - c1,
                  "counts": dict(res.counts), "timings": res.timings}))
"""


def read_copy_seconds(path, reader: str = "h5py") -> tuple[float, float]:
    """(wall, CPU) seconds to read ``/shots/bins`` in chunks of 8192 shots and copy each
    chunk, in a fresh process: with h5py (HDF5's zlib filter; the issue's measure),
    or ``reader="libdeflate"``, the package's reader of gzip'd chunks
    (:mod:`mems_stereo.io.deflate_chunks`, which the pipeline uses where it can)."""
    r = measure_child(READ_COPY, path, *([] if reader == "h5py" else [reader]))
    return r["seconds"], r["cpu_s"]


def process_in_child(path) -> dict:
    """``process_recording`` of ``path`` in a fresh process: seconds, stages, peak RSS."""
    return measure_child(PROCESS, path)


if __name__ == "__main__":  # quick look: python benchmarks/_dense.py OUT.h5 N SEED
    info = make_dense_recording(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
    print(json.dumps(info))
