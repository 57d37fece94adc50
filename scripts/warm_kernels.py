"""Compile the package's numba kernels into numba's disk cache once (scripts/setup.sh).

A fresh clone has no cache (numba keeps it beside the sources, in ``__pycache__``):
without this step each test process compiles every kernel it meets, and the two
pytest-xdist workers each pay it (tens of CPU seconds each; benchmarks/results/
test_suite_time.log).  This script runs the bundled samples through the paths that
compile (a dense one-axis recording and a sparse one, whole and in frames, a two-axis
recording: 25 kernels), so that later processes load those kernels from the cache;
kernels only some tests force on (small inputs, signal stores) are still compiled
where first met.  A kernel's cache entry is invalidated when its
source file changes; numba then compiles it again on first use, as without this step.

Usage: ``python scripts/warm_kernels.py`` (prints the CPU seconds it took).
"""

from __future__ import annotations

import os
import resource
import time


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")  # as tests/conftest.py
    os.environ.setdefault("MPLBACKEND", "Agg")
    c0, t0 = _cpu(), time.perf_counter()
    from mems_stereo import data
    from mems_stereo.pipeline.frames import iter_frames
    from mems_stereo.pipeline.run import process_recording
    from mems_stereo.pipeline.twoaxis import process_recording_2d

    for name in ("floodlight.h5", "room.h5"):
        process_recording(data.path(name))
        for _ in iter_frames(data.path(name), frame_rate=10.0):
            pass
    process_recording_2d(data.path("lissajous64.h5"))
    print(f"[warm_kernels] numba kernels cached: {_cpu() - c0:.1f} CPU s, "
          f"{time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
