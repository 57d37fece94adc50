"""Scale-out on Dask distributed: many recordings, or one large recording split by shots.

The same stage functions as :mod:`mems_stereo.pipeline.run` run on workers over
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

from mems_stereo.io.recording import read_header
from mems_stereo.model.system import System
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.intervals import install_tables, interval_table, table_key
from mems_stereo.pipeline.pass1 import accumulate_range
from mems_stereo.pipeline.pass2 import peak_counts_range
from mems_stereo.pipeline.run import ProcessResult, finish_processing, process_recording
from mems_stereo.pipeline.settings import Settings


@contextlib.contextmanager
def dask_client(scheduler="local", n_workers: int = 2):
    """A Dask client for ``scheduler`` (see module docstring); closes what it started."""
    from distributed import Client, LocalCluster

    if isinstance(scheduler, Client):
        yield scheduler
        return
    if scheduler in (None, "local"):
        import dask

        env = {"NUMBA_THREADING_LAYER": "omp", "OMP_NUM_THREADS": "1"}
        os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
        # Dask's nannies set MALLOC_TRIM_THRESHOLD_=65536 by default: glibc then
        # returns every large temporary to the OS and page-faults it back, which
        # measured 2x slower on this pipeline's NumPy stages; keep glibc's default.
        with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_":
                              None}), \
                LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                             dashboard_address=None, env=env) as cluster, \
                Client(cluster) as client:
            yield client
        return
    with Client(scheduler) as client:
        yield client


def _tables_for(systems, settings: Settings) -> dict:
    """Filled interval tables of the given systems, keyed as the workers' caches are."""
    out = {}
    for sysm in systems:
        key = table_key(sysm, settings.confidence, min_range=settings.min_range)
        if key not in out:
            out[key] = interval_table(sysm, settings.confidence,
                                      min_range=settings.min_range).fill_all()
    return out


def _process_task(path, system, settings, tables):
    install_tables(tables)
    return process_recording(path, system=system, settings=settings)


def process_many(paths: Sequence, system: System | None = None,
                 settings: Settings | None = None, scheduler="local",
                 n_workers: int = 2) -> list[ProcessResult]:
    """Process several recordings on a Dask cluster, one task each (results in order).

    The interval tables of the recordings' systems are filled once here and
    broadcast to the workers, so no worker spends time compiling them.
    """
    st = Settings() if settings is None else settings
    systems = [system] if system is not None else [read_header(p).system for p in paths]
    tables = _tables_for(systems, st)
    with dask_client(scheduler, n_workers) as client:
        tables_f = client.scatter(tables, broadcast=True)
        futures = client.map(_process_task, [str(p) for p in paths], system=system,
                             settings=st, tables=tables_f, pure=False)
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
    tables = _tables_for([sysm], st)
    with dask_client(scheduler, n_workers) as client:
        t0 = time.perf_counter()
        client.run(install_tables, tables)
        th_f, va_f = client.scatter([theta, valid], broadcast=True)
        accs = client.gather([client.submit(accumulate_range, str(path), sysm, th_f, va_f, st,
                                            a, b, pure=False) for a, b in parts])
        acc = accs[0]
        for a in accs[1:]:
            acc = acc + a
        timings["classify_histogram"] = time.perf_counter() - t0

        def count_peaks(peaks):
            # pass 2 needs only the pixels, windows and bands; send them once
            light = {k: v for k, v in peaks.items() if k != "background_by_step"}
            pk_f = client.scatter([light], broadcast=True)[0]
            parts_pc = client.gather([
                client.submit(peak_counts_range, str(path), sysm, th_f, va_f, st, pk_f, a, b,
                              pure=False) for a, b in parts])
            total = parts_pc[0]
            for p in parts_pc[1:]:
                total = total + p
            return total

        return finish_processing(path, sysm, header, theta, valid, acc, st, timings,
                                 count_peaks=count_peaks)
