"""Scale-out on Dask distributed: many recordings, or one large recording split by shots.

The same stage functions as :mod:`mems_stereo.pipeline.run` run on workers over
shot ranges; their results add exactly (histograms, counts and peak counts
are integers), so the outcome is identical to one process, bit for bit.

* :func:`process_many` — one task per recording.
* :func:`process_split` — one recording split into shot ranges: pass 1
  (classify + histograms) per range, the peak detector per block of pixels
  (the client joins the few numbers per pixel of its neighbour support and
  confirms the matched filter's candidates), pass 2 (peak counts) per range,
  the fusion per block of peaks, all on the workers; the client joins the
  blocks' peak means and makes the cloud.

The modules beside this one, one per concern: :mod:`~mems_stereo.pipeline.dask_setup`
(the client and cluster), :mod:`~mems_stereo.pipeline.dask_plan` (the parts, blocks
and slots), :mod:`~mems_stereo.pipeline.dask_reduce` (sums on the workers),
:mod:`~mems_stereo.pipeline.dask_tasks` (what the workers run) and
:mod:`~mems_stereo.pipeline.dask_split` (the client's steps of :func:`process_split`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import replace

import h5py

from mems_stereo.io.recording import read_header, read_system
from mems_stereo.model.system import System, system_to_json
from mems_stereo.pipeline.dask_setup import ClientWaits, dask_client
from mems_stereo.pipeline.dask_split import (
    CandidatesOnWorkers,
    count_candidates_on_workers,
    count_peaks_on_workers,
    detect_on_workers,
    fill_table,
    gather_angles,
    join_fusion,
    pass1_on_workers,
    score_on_workers,
    start_parts,
    submit_fusion,
)
from mems_stereo.pipeline.dask_tasks import process_task
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.run import (
    TRIM_SLOTS,
    CandidateCounts,
    Histograms,
    ProcessResult,
    RunInputs,
    matched_stage,
    result_of,
    run_table,
)
from mems_stereo.pipeline.settings import Settings
from mems_stereo.util.memory import HeapTrimmer
from mems_stereo.util.stopwatch import Stopwatch

__all__ = ["dask_client", "process_many", "process_split"]


def process_many(paths: Sequence, system: System | None = None,
                 settings: Settings | None = None, scheduler="local",
                 n_workers: int = 2) -> list[ProcessResult]:
    """Process several recordings on a Dask cluster, one task each (results in order).

    The interval table of each distinct system is filled once, on the workers
    in parallel, and scattered to every worker, so no task computes one.  The
    tasks are submitted largest recording first (longest processing time first),
    so that recordings of unequal lengths balance over the workers.
    """
    st = Settings() if settings is None else settings
    systems = [system] * len(paths) if system is not None else [read_system(p) for p in paths]
    with dask_client(scheduler, n_workers) as client:
        tables, keys = {}, []
        for sysm in systems:
            key = system_to_json(sysm)
            if key not in tables:
                tables[key] = fill_table(client, IntervalTable.for_settings(sysm, st),
                                         settings=st)
            keys.append(key)
        scattered = {k: client.scatter(t, broadcast=True) for k, t in tables.items()}
        # Dask starts tasks in the order submitted: the last to start are the short ones
        # and the workers finish together
        order = sorted(range(len(paths)), key=lambda i: -recording_slots(paths[i]))
        futures = [None] * len(paths)
        for i in order:
            futures[i] = client.submit(process_task, str(paths[i]), system, st,
                                       scattered[keys[i]], pure=False)
        return client.gather(futures)


def recording_slots(path) -> int:
    """Pixel-slots of a recording (its ``/shots/bins`` size; 0 where unreadable: the
    task then reports the error), read without the shots."""
    try:
        with h5py.File(path, "r") as f:
            return int(f["shots/bins"].size)
    except Exception:  # noqa: BLE001 - the task itself raises the package's error
        return 0


class ClientUsage:
    """The client's own time over a split run: wall, CPU of its process and of its
    calling thread, and its waits on the workers (:class:`ClientWaits`)."""

    def __init__(self):
        self.wall = time.perf_counter()
        self.cpu = time.process_time()
        self.thread = time.thread_time()
        self.run_start = self.wall
        self.waits = ClientWaits()

    def start_run(self) -> None:
        """Mark the start of the run proper (a local cluster's start-up is not the run's)."""
        self.run_start = time.perf_counter()

    def timings(self, read_header_s: float) -> dict[str, float]:
        """The client's figures so far (see :func:`process_split`)."""
        return {"client_serial": read_header_s + (time.perf_counter() - self.run_start)
                - self.waits.seconds,
                "client_wait": self.waits.seconds,
                "client_waits": float(self.waits.count),
                "client_cpu": time.process_time() - self.cpu,
                "client_main_cpu": time.thread_time() - self.thread}


def process_split(path, system: System | None = None, settings: Settings | None = None,
                  scheduler="local", n_workers: int = 2, n_parts: int | None = None
                  ) -> ProcessResult:
    """Process one (large) recording split by shot ranges over Dask workers.

    Each shot range's scan angles (from its shot times, on its worker) and
    pass 1, reduced and scattered by blocks of pixels on the workers; the peak
    detector per block of pixels on the workers (the neighbour support and the
    matched filter's confirmation on the client); pass 2 per shot range (from
    its signal store), its selections summed on the workers; the fusion per
    block of peaks on the workers, dealt to the workers' slots, the client only
    joining the blocks' means.  The result is the one process's, bit for bit.
    ``n_parts`` : shot ranges (default: one per worker,
    :data:`~mems_stereo.pipeline.dask_plan.PARTS_PER_WORKER`).

    ``timings`` of the result add the client's own serial seconds
    (``client_serial``: the wall time less the time it waited on its workers,
    ``client_wait``; ``client_waits``: how many times it blocked on them), the CPU
    seconds of the client process over the run (``client_cpu``: all its threads,
    with a local cluster's scheduler) and of its calling thread
    (``client_main_cpu``), the bytes it received (``client_bytes``), ``parts`` and
    ``peak_blocks``; ``peaks_wait`` : of the peak stage's seconds (``peaks``), those
    spent waiting on the workers.  Pass 2 runs on the workers while the fusion's
    tasks are submitted, so ``points`` holds pass 2 and the fusion and
    ``peak_detections`` only the submission.
    """
    st = Settings() if settings is None else settings
    usage, clock = ClientUsage(), Stopwatch()
    header = read_header(path)  # (validates the shot times and zero crossings)
    sysm = header.system if system is None else system
    header.shot_time = None  # each part computes its own shots' angles
    timings = {"read_header": clock.lap()}
    table = run_table(sysm, st)
    trim = HeapTrimmer(math.prod(header.shape) >= TRIM_SLOTS)
    with dask_client(scheduler, n_workers) as client:
        usage.start_run()
        clock.lap()
        run = start_parts(client, str(path), header, sysm, st, table, n_parts, usage.waits)
        timings["table"] = clock.lap()
        p1 = pass1_on_workers(run)
        acc, stores = p1.acc, p1.stores
        timings["classify_histogram"] = clock.lap()
        hists = trim.after(Histograms.of(acc, *header.shape[1:]))
        waited = usage.waits.seconds
        found = trim.after(detect_on_workers(run, p1))
        del p1  # the blocks' (P, S) scores: released on the workers
        cc = count_candidates_on_workers(run, found.peaks, stores)
        scores = None if cc is None else score_on_workers(run, cc, acc.n_per_step)
        peaks = matched_stage(sysm, found.peaks, _client_side(cc), table, acc.n_per_step, st,
                              scores)
        timings["peaks"] = clock.lap()
        timings["peaks_wait"] = usage.waits.seconds - waited
        counted = trim.after(count_peaks_on_workers(run, found.peaks, cc, peaks, stores))
        del stores  # released once their pass 2 has run
        timings["peak_detections"] = clock.lap()
        means_f = submit_fusion(run, counted, len(peaks), acc.n_per_step)
        theta, valid = gather_angles(run, header.shape[0])  # while the blocks are fused
        fused = join_fusion(run, means_f, peaks, acc.n_per_step)
        peaks = replace(peaks, background_by_step=None)  # (Q, S): used up
        timings["points"] = clock.lap()
        timings |= usage.timings(timings["read_header"])
    timings |= {"client_bytes": float(sum(a.nbytes for a in (acc.hist_raw, acc.hist_signal,
                                                              acc.hist_angle))
                                      + fused.nbytes + found.nbytes),
                "parts": float(len(run.parts)), "peak_blocks": float(fused.n_blocks)}
    return result_of(RunInputs(str(path), sysm, st, table, theta, valid, header.shape), acc,
                     hists, found.background, peaks, fused.cloud, timings)


def _client_side(cc: CandidatesOnWorkers | None) -> CandidateCounts | None:
    """The candidates for :func:`matched_stage` (their counts stay on the workers, where
    their scores are computed)."""
    return None if cc is None else CandidateCounts(cc.candidates, None)
