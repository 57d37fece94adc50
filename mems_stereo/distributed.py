"""Scale-out on Dask distributed: many recordings, or one large recording split by shots.

The same stage functions as :mod:`mems_stereo.pipeline` run on workers over
shot ranges; their results add exactly (histograms, counts and peak counts
are integers), so the outcome is identical to one process, bit for bit.

* :func:`process_many` — one task per recording.
* :func:`process_split` — one recording split into shot ranges: pass 1
  (classify + histograms) per range, peaks on the client, pass 2 (peak
  counts) per range, points on the client.

``scheduler`` is ``"local"`` (a :class:`distributed.LocalCluster` of
``n_workers`` single-threaded processes, started and closed here) or the
address of an existing scheduler (``tcp://host:8786``), or a ready
:class:`distributed.Client`.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Sequence

import numpy as np

from .pipeline import (
    ProcessResult,
    Settings,
    accumulate_range,
    finish_processing,
    peak_counts_range,
    process_recording,
    shot_angles,
)
from .recording import read_header
from .system import System


@contextlib.contextmanager
def dask_client(scheduler="local", n_workers: int = 2):
    """A Dask client for ``scheduler`` (see module docstring); closes what it started."""
    from distributed import Client, LocalCluster

    if isinstance(scheduler, Client):
        yield scheduler
        return
    if scheduler in (None, "local"):
        env = {"NUMBA_THREADING_LAYER": "omp", "OMP_NUM_THREADS": "1"}
        os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
        with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                          dashboard_address=None, env=env) as cluster, \
                Client(cluster) as client:
            yield client
        return
    with Client(scheduler) as client:
        yield client


def process_many(paths: Sequence, system: System | None = None,
                 settings: Settings | None = None, scheduler="local",
                 n_workers: int = 2) -> list[ProcessResult]:
    """Process several recordings on a Dask cluster, one task each (results in order)."""
    st = Settings() if settings is None else settings
    with dask_client(scheduler, n_workers) as client:
        futures = client.map(process_recording, [str(p) for p in paths], system=system,
                             settings=st, pure=False)
        return client.gather(futures)


def shot_ranges(n_shots: int, n_parts: int) -> list[tuple[int, int]]:
    """Split 0..n_shots into ``n_parts`` contiguous ranges of nearly equal length."""
    edges = np.linspace(0, n_shots, max(1, int(n_parts)) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def process_split(path, system: System | None = None, settings: Settings | None = None,
                  scheduler="local", n_workers: int = 2, n_parts: int | None = None
                  ) -> ProcessResult:
    """Process one (large) recording split by shot ranges over Dask workers."""
    st = Settings() if settings is None else settings
    header = read_header(path)
    sysm = header.system if system is None else system
    theta, valid = shot_angles(header, sysm)
    K = header.shape[0]
    parts = shot_ranges(K, n_parts or 4 * n_workers)
    timings = {}
    with dask_client(scheduler, n_workers) as client:
        t0 = time.perf_counter()
        th_f, va_f = client.scatter([theta, valid], broadcast=True)
        accs = client.gather([client.submit(accumulate_range, str(path), sysm, th_f, va_f, st,
                                            a, b, pure=False) for a, b in parts])
        acc = accs[0]
        for a in accs[1:]:
            acc = acc + a
        timings["classify_histogram"] = time.perf_counter() - t0

        def count_peaks(peaks):
            parts_pc = client.gather([
                client.submit(peak_counts_range, str(path), sysm, th_f, va_f, st, peaks, a, b,
                              pure=False) for a, b in parts])
            total = parts_pc[0]
            for p in parts_pc[1:]:
                total = total + p
            return total

        return finish_processing(path, sysm, header, theta, valid, acc, st, timings,
                                 count_peaks=count_peaks)
