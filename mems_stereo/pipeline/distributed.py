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

What keeps the client's serial share small (``docs/throughput.md``):

* the interval table of a run is built once: its rows are computed by the
  workers in parallel (:func:`fill_table`), assembled on the client and
  scattered to every worker once;
* each part receives only its own slice of the scan angles;
* the parts' pass-1 results are reduced and scattered by blocks of pixels on
  the workers (each part's rows of a block sliced where the part lies, each
  block's slices summed on the block's worker, where the peak detector's
  per-pixel stage then runs), and pass 2's in a tree of groups of
  :data:`FAN_IN` (:func:`tree_sum`), so the client receives one pass-1 result
  (without the per-angle counts) and one pass-2 result whatever the number of
  parts; the pass-1 counts travel as uint32, as their non-zero entries where
  that is smaller;
* each part keeps its signal detections on its worker
  (:class:`~mems_stereo.pipeline.signal_store.SignalStore`), and its pass 2
  counts from them instead of reading the shots again — one pass for the
  first stage's peaks and the matched filter's candidates together
  (:func:`select_counts` filters each set's counts from it);
* the peak detector's per-pixel stages run in blocks of pixels on the workers
  (:func:`~mems_stereo.pipeline.peaks.peak_scores`,
  :func:`~mems_stereo.pipeline.peaks.peaks_of_scores`), so the (P, S)
  per-angle counts never reach the client;
* pass 2's sum stays on the workers: it is split by blocks of peaks there
  (:func:`split_peak_counts`) and each block is fused on a worker, without
  a halo, up to each peak's means (``PeakMeans``); the client joins the
  means and makes the cloud (the depth edges look across blocks).

``scheduler`` is ``"local"`` (a :class:`distributed.LocalCluster` of
``n_workers`` single-threaded processes, started and closed here) or the
address of an existing scheduler (``tcp://host:8786``), or a ready
:class:`distributed.Client`.
"""

from __future__ import annotations

import contextlib
import operator
import os
import time
from collections.abc import Sequence

import numpy as np

from mems_stereo.errors import OptionError
from mems_stereo.io.recording import read_header, read_system
from mems_stereo.model.system import System, system_to_json
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.pass1 import COMPILE_SLOTS, accumulate_range
from mems_stereo.pipeline.pass2 import (
    PeakCounts,
    candidate_selection,
    merged_selection,
    peak_counts_range,
    peak_fields,
    select_counts,
    with_widened_candidates,
)
from mems_stereo.pipeline.peaks import concat_peaks, peak_scores, peaks_of_scores, supported
from mems_stereo.pipeline.run import (  # noqa: F401 - peak_blocks: part of this API
    ProcessResult,
    cloud_of_means,
    finish_processing,
    fusion_work,
    join_clouds,
    means_block,
    peak_blocks,
    points_block,
    process_recording,
    split_peak_counts,
)
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.signal_store import (
    SignalStore,
    peak_counts_from_store,
    rereading_decompresses,
)

#: seconds a remote scheduler's handshake may take
SCHEDULER_CONNECT_TIMEOUT = 10.0

#: parts summed per task of the reduction tree
FAN_IN = 4

#: shot ranges of :func:`process_split` per worker (default of ``n_parts``): one.  More
#: parts cost each their pass-1 arrays, their tasks on the client and their transfers
#: (400,000 dense shots on 2 workers: 3.46 s of worker CPU with 2 parts, 3.68 with 4,
#: 3.95-4.25 with 8, against 3.65 s in one process; the client 0.51 -> 0.75-0.96 s)
PARTS_PER_WORKER = 1

#: blocks of peaks fused per worker (at most: blocks are cut at multiples of
#: ``FP_BLOCK`` peaks), dealt to the workers' slots by their work (:func:`block_slots`)
BLOCKS_PER_WORKER = 4

#: blocks of pixels per worker in which :func:`process_split` runs the peak detector
#: (its per-pixel stages; the neighbour support between them on the client)
PEAK_BLOCKS_PER_WORKER = 1
#: blocks of the matched filter's candidates scored per worker (their whole-scan
#: searches differ in cost: a few blocks each even the load)
SCORE_BLOCKS_PER_WORKER = 2

#: Dask settings of the LocalCluster that :func:`dask_client` starts (see there)
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                        "distributed.admin.tick.interval": "200ms",
                        "distributed.worker.memory.monitor-interval": "1s",
                        "distributed.admin.system-monitor.interval": "2s"}


#: glibc settings of the LocalCluster's worker processes (see :func:`dask_client`;
#: workers of a remote cluster are best started with them too)
WORKER_MALLOC_ENV = {"MALLOC_ARENA_MAX": "1"}


def _restore_environ(saved: dict) -> None:
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


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
        # The housekeeping of a local cluster, which shares the cores with the work:
        # no statistical profiler on the workers (it samples the running task's stack
        # every 10 ms: a third of an idle worker's CPU, more while it works), and the
        # event loops' tick and the memory and system monitors less often (an idle
        # worker 2.1 % -> 0.5 % of a core, the client with the scheduler 3.8 % -> 1.2 %)
        # One malloc arena per worker (WORKER_MALLOC_ENV): a worker runs its tasks in a
        # thread of its own, whose glibc arena hands the heaps of freed temporaries
        # back to the OS and page-faults them in again on every task (1,600,000 dense
        # shots, pass 1 on one worker: 52,000 page faults, 0.3-0.4 s of system time
        # more than in one process; none with one arena).  Read by glibc when the
        # process starts, so set before the spawn (Dask's pre-spawn environment,
        # which also lands in this process's os.environ: restored afterwards)
        saved = {k: os.environ.get(k) for k in WORKER_MALLOC_ENV}
        try:
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_":
                                  None, **{f"distributed.nanny.pre-spawn-environ.{k}": v
                                           for k, v in WORKER_MALLOC_ENV.items()},
                                  **LOCAL_CLUSTER_CONFIG}), \
                    LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                 dashboard_address=None, env=env) as cluster:
                _restore_environ(saved)
                with Client(cluster) as client:
                    yield client
        finally:
            _restore_environ(saved)
        return
    try:
        client = Client(scheduler, timeout=SCHEDULER_CONNECT_TIMEOUT)
    except Exception as e:  # noqa: BLE001 - the handshake's faults vary with what answered
        # e.g. an HTTP server on that port: Dask reads its bytes as a frame length
        # and asks for exabytes (MemoryError), or times out, or is refused
        why = "it answered, but not as a Dask scheduler" if isinstance(
            e, (MemoryError, ValueError, TypeError)) else (str(e) or type(e).__name__)
        raise OptionError(f"cannot connect to a Dask scheduler at {scheduler}: {why}",
                          field="--scheduler") from None
    with client:
        yield client


def _n_workers(client) -> int:
    return max(1, len(client.scheduler_info().get("workers", {})))


def _worker_addresses(client) -> list:
    """The cluster's worker addresses, sorted (empty where the scheduler lists none)."""
    return sorted(client.scheduler_info().get("workers", {}))


def _sum(*parts):
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total


def tree_sum(client, futures: list, fan_in: int = FAN_IN):
    """One future of the sum of ``futures``, summed on the workers in groups of ``fan_in``.

    Exact for integer results (any grouping gives the same sum); the client
    only ever receives the final sum.
    """
    futures = tree_reduce(client, futures, fan_in, fan_in)
    return futures[0] if len(futures) == 1 else client.submit(_sum, *futures, pure=False)


def tree_reduce(client, futures: list, most: int, fan_in: int = FAN_IN) -> list:
    """``futures`` summed on the workers in groups of ``fan_in`` until at most ``most``
    remain (a list): a task that sums them itself before its own work saves the
    last sum's round trip."""
    futures = list(futures)
    while len(futures) > max(1, most):
        futures = [futures[i] if len(futures[i:i + fan_in]) == 1 else
                   client.submit(_sum, *futures[i:i + fan_in], pure=False)
                   for i in range(0, len(futures), fan_in)]
    return futures


def _split_candidates_of_sum(edges, n_steps, n_codes, *parts):
    """:func:`~mems_stereo.pipeline.matched.split_candidate_counts` of the parts' sum."""
    from mems_stereo.pipeline.matched import split_candidate_counts

    return split_candidate_counts(_sum(*parts), edges, n_steps, n_codes)


def _split_peaks_of_sum(n_peaks, n_steps, n_codes, n_workers, per_worker, *parts):
    """``(blocks, slots)``: :func:`split_peak_counts` of the parts' sum in at most
    ``n_workers * per_worker`` blocks, and :func:`block_slots` of them: the block that
    slot s (run on worker s mod ``n_workers``) fuses, dealt here by the blocks' work
    (:func:`_block_work`), so that the client submits the slots' tasks at once,
    without waiting for the work to come back."""
    blocks = split_peak_counts(_sum(*parts), n_peaks, n_steps, n_codes,
                               n_workers * per_worker)
    return blocks, block_slots(_block_work(blocks, n_steps, n_codes), n_workers, per_worker)


def _table_rows(system: System, settings: Settings, rows):
    table = IntervalTable.for_settings(system, settings)
    return table.compute_rows(rows)


def fill_table(client, table: IntervalTable, rows=None, settings: Settings | None = None,
               waits=None) -> IntervalTable:
    """Fill ``rows`` (default: all) of ``table`` on the workers in parallel; returns it.

    Rows in the disk cache are taken from it; the others are split into one
    contiguous block per worker; each worker computes its block with the
    reference (:meth:`IntervalTable.compute_rows`, identical to filling here),
    the client stores them and writes them to the cache.
    """
    table.load_cache()
    need = table.missing(np.arange(table.n_steps) if rows is None else rows)
    if need.size == 0:
        return table
    st = settings if settings is not None else Settings(table.confidence,
                                                        min_range=table.min_range)
    blocks = [b for b in np.array_split(need, _n_workers(client)) if b.size]
    futs = client.map(_table_rows, [table.system] * len(blocks), [st] * len(blocks), blocks,
                      pure=False)
    got = client.gather(futs) if waits is None else waits(client.gather, futs)
    for b, (lo, hi) in zip(blocks, got):
        table.put_rows(b, lo, hi)
    table.save_cache()
    return table


def _process_task(path, system, settings, table):
    return process_recording(path, system=system, settings=settings, table=table)


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
        # the largest recordings first (Dask starts tasks in the order submitted): the
        # longest-processing-time-first order, so that the last tasks to start are the
        # short ones and the workers finish together
        order = sorted(range(len(paths)), key=lambda i: -_n_slots(paths[i]))
        futures = [None] * len(paths)
        for i in order:
            futures[i] = client.submit(_process_task, str(paths[i]), system, st,
                                       scattered[keys[i]], pure=False)
        return client.gather(futures)


def _n_slots(path) -> int:
    """Pixel-slots of a recording (its ``/shots/bins`` size; 0 where unreadable: the
    task then reports the error), read without the shots."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return int(f["shots/bins"].size)
    except Exception:  # noqa: BLE001 - the task itself raises the package's error
        return 0


def shot_ranges(n_shots: int, n_parts: int) -> list[tuple[int, int]]:
    """Split 0..n_shots into ``n_parts`` contiguous ranges of nearly equal length."""
    edges = np.linspace(0, n_shots, max(1, int(n_parts)) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


class _Waits:
    """Seconds the client spends blocked on its workers' results, and how many times."""

    def __init__(self):
        self.seconds = 0.0
        self.count = 0

    def __call__(self, fn, *args):
        self.count += 1
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.seconds += time.perf_counter() - t


def process_split(path, system: System | None = None, settings: Settings | None = None,
                  scheduler="local", n_workers: int = 2, n_parts: int | None = None
                  ) -> ProcessResult:
    """Process one (large) recording split by shot ranges over Dask workers.

    Each shot range's scan angles (from its shot times, on its worker) and
    pass 1, reduced and scattered by blocks of pixels on the workers; the peak
    detector per block of pixels on the workers (the neighbour support and the
    matched filter's confirmation on the client); pass 2 per shot range (from
    its signal store), its selections summed on the workers; the fusion per
    block of peaks on the workers (:func:`split_peak_counts`, dealt to the
    workers' slots by :func:`block_slots`), the client only joining the
    blocks' means.  The result is the one process's, bit for bit.
    ``n_parts`` : shot ranges (default: one per worker, :data:`PARTS_PER_WORKER`).
    ``timings`` of the result add the client's own serial seconds
    (``client_serial``: the wall time less the time it waited on its workers,
    ``client_wait``; ``client_waits``: how many times it blocked on them), the CPU
    seconds of the client process over the run
    (``client_cpu``: all its threads, with a local cluster's scheduler) and of
    its calling thread (``client_main_cpu``), the bytes it received
    (``client_bytes``), ``parts`` and ``peak_blocks``; ``peaks_wait`` : of the
    peak stage's seconds (``peaks``), those spent waiting on the workers.  Pass 2
    runs on the workers while the fusion's tasks are submitted, so ``points``
    holds pass 2 and the fusion and ``peak_detections`` only the submission.
    """
    st = Settings() if settings is None else settings
    t_all = time.perf_counter()
    c_all = time.process_time()
    m_all = time.thread_time()
    waits = _Waits()
    header = read_header(path)  # (validates the shot times and zero crossings)
    sysm = header.system if system is None else system
    header.shot_time = None  # each part computes its own shots' angles (below)
    K = header.shape[0]
    timings = {"read_header": time.perf_counter() - t_all}
    table = IntervalTable.for_settings(sysm, st)
    table.load_cache()
    S, n_codes = table.n_steps, sysm.tdc.n_bins + 1
    # the shots' angles, filled from the parts' (see make_points: the result's)
    theta = np.empty(K, np.float64)
    valid = np.zeros(K, bool)
    with dask_client(scheduler, n_workers) as client:
        t_run = time.perf_counter()  # (a local cluster's start-up is not the run's)
        n_w = _n_workers(client)
        parts = shot_ranges(K, n_parts or n_w * PARTS_PER_WORKER)
        t0 = time.perf_counter()
        # each part's angles computed on the workers from its shot times (the same
        # elementwise arithmetic as shot_angles here) and kept there for its passes;
        # the table's rows they need and lack (none once the cache holds them all) are
        # filled on the workers first.  The client computes and sends no angle.
        table_f = client.scatter(table, broadcast=True)
        zc_f = _scatter_one(client, (header.zero_crossings, header.rising))
        complete = bool(table.filled.all())  # then nothing can be missing: no round trip
        ang_missing = [client.submit(_part_angles, str(path), sysm, zc_f, a, b,
                                     None if complete else table_f, pure=False)
                       for a, b in parts]
        angle_f = [client.submit(operator.itemgetter(0), f, pure=False) for f in ang_missing]
        if not complete:
            need = np.unique(np.concatenate(waits(client.gather, [
                client.submit(operator.itemgetter(1), f, pure=False) for f in ang_missing])))
            if need.size:
                fill_table(client, table, need, settings=st, waits=waits)
                table_f = client.scatter(table, broadcast=True)
        del ang_missing
        timings["table"] = time.perf_counter() - t0

        t1 = time.perf_counter()
        # the parts' sum reduced and scattered by blocks of pixels: each part slices its
        # rows of each block where it lies (``_pass1_part``: its signal store first,
        # then one slice per block), and each block's slices are summed on the block's
        # worker (no part's whole arrays move, no worker sums the whole); there the
        # peak detector's per-pixel stage runs on its block, while the client gathers
        # what it needs of pass 1 (the (P, S) per-angle counts stay on the workers).
        # Each part keeps its signal detections on its worker for its pass 2
        # (SignalStore: no second read of the shots; compiled-size parts only)
        P = sysm.receiver.width * sysm.receiver.height
        edges = shot_ranges(P, min(P, n_w * PEAK_BLOCKS_PER_WORKER))
        addr = _worker_addresses(client)
        p1 = [client.submit(_pass1_part, str(path), sysm, ang, st, a, b, table_f, edges,
                            pure=False) for ang, (a, b) in zip(angle_f, parts)]
        stores = [client.submit(operator.itemgetter(0), f, pure=False) for f in p1]
        blocks_p1 = [client.submit(_block_rows,
                                   *[client.submit(operator.getitem, f, 1 + i, pure=False)
                                     for f in p1], pure=False,
                                   workers=[addr[i % len(addr)]] if addr else None,
                                   allow_other_workers=True)
                     for i in range(len(edges))]
        del p1
        scores_f = [client.submit(_scores_block, b, sysm, st, table_f, p0, p1, pure=False,
                                  workers=[addr[i % len(addr)]] if addr else None,
                                  allow_other_workers=True)
                    for i, (b, (p0, p1)) in enumerate(zip(blocks_p1, edges))]
        sup_f = [client.submit(_support_inputs, f, pure=False) for f in scores_f]
        acc = _joined_pixel_blocks(waits(client.gather, [
            client.submit(operator.itemgetter(1), b, pure=False) for b in blocks_p1]))
        del blocks_p1
        timings["classify_histogram"] = time.perf_counter() - t1
        nbytes = sum(a.nbytes for a in (acc.hist_raw, acc.hist_signal, acc.hist_angle))
        shared = {}

        def detect(sig, noise):
            # the client joins the few numbers per pixel that the neighbour support
            # needs, then each block makes its peaks (the same as find_peaks on the
            # whole, bit for bit)
            shared["wait_peaks"] = waits.seconds
            sup = waits(client.gather, sup_f)
            keep = supported(*(np.concatenate(x) for x in zip(*(s[:4] for s in sup))),
                             sysm.receiver.width)
            parts = waits(client.gather, [
                client.submit(peaks_of_scores, sysm, f, keep[p0:p1], acc.n_per_step, table_f,
                              st, pure=False) for f, (p0, p1) in zip(scores_f, edges)])
            scores_f.clear()  # each block's (P, S) arrays: released on the workers
            detect.nbytes = sum(sum(a.nbytes for a in s) for s in sup)
            rate = np.concatenate([s[4] for s in sup])
            peaks = concat_peaks(parts)
            shared["first"] = peaks  # the first stage's peaks (see count_candidates)
            return peaks, rate.reshape(sysm.receiver.height, sysm.receiver.width)

        def pass2_parts(peaks_f):
            # each part counts the windows of ``peaks_f`` (its store or its shots): one
            # future per part, on the part's worker
            return [client.submit(_pass2_part, str(path), sysm, ang, st, peaks_f, a, b,
                                  table_f, store, pure=False)
                    for ang, (a, b), store in zip(angle_f, parts, stores)]

        def pass2_sum(peaks_f):
            # the parts' counts summed on the workers: one future
            return tree_sum(client, pass2_parts(peaks_f))

        def selected_parts(parts_f, sel):
            # select_counts of each part where it lies; the (smaller) selections are
            # summed by the task that reads them (the selection of the sum: each key's
            # count is its parts' sum), after a tree down to FAN_IN of them
            return tree_reduce(client, [client.submit(select_counts, f, *sel, S, n_codes,
                                                      pure=False) for f in parts_f], FAN_IN)

        def count_peaks(peaks):
            # (the peak stage ends here: what of it the client spent waiting on workers)
            timings["peaks_wait"] = waits.seconds - shared.get("wait_peaks", waits.seconds)
            both_f = shared.get("both_f")
            if both_f is None:
                # pass 2 needs only the pixels, windows and bands; send them once
                shared["peaks"] = _scatter_one(client, peak_fields(peaks))
                total_f = [pass2_sum(shared["peaks"])]
            else:
                # the first stage's peaks and the candidates' widened windows were counted
                # in one pass (count_candidates): the first stage's counts renumbered into
                # the order of ``peaks``, each confirmed peak's filtered to its window
                # (each peak's counts are its own: the PeakCounts of counting ``peaks``)
                sel = merged_selection(shared["first"], shared["cands"], peaks,
                                       sysm.receiver.width)
                total_f = selected_parts(both_f, sel)
                shared.pop("both_f")
                # the fusion's blocks read the peaks' fields: sent once, while the
                # selections run (a scatter waits for its data to arrive)
                shared["peaks"] = _scatter_one(client, peak_fields(peaks))
            stores.clear()  # released once their pass 2 has run
            return total_f  # futures of counts to sum: they stay on the workers

        def make_points(peaks, total_f):
            Q = len(peaks["row"])
            nps_f = client.scatter(acc.n_per_step, broadcast=True)
            # the counts summed and split into blocks of peaks by one task, which also
            # deals them to the workers' slots by their work, the largest first to the
            # least loaded (cuts at multiples of FP_BLOCK peaks leave blocks of unequal
            # work); the slots' tasks are submitted with it, each pinned to its worker,
            # so no round trip comes between.  Left to itself the scheduler runs every
            # block where the blocks lie (data locality): one worker fused most of them
            # (2 workers, 1,600,000 shots: 4.55 / 5.25 s of CPU)
            addr = _worker_addresses(client)
            n_slot_w = max(1, len(addr))
            split_f = client.submit(_split_peaks_of_sum, Q, S, n_codes, n_slot_w,
                                    BLOCKS_PER_WORKER, *total_f, pure=False)
            means_f = [client.submit(_means_of_slot, sysm, shared["peaks"], split_f, i,
                                     st, nps_f, table_f, pure=False,
                                     workers=[addr[i % n_slot_w]] if addr else None,
                                     allow_other_workers=True)
                       for i in range(n_slot_w * BLOCKS_PER_WORKER)]
            # the shots' angles gathered from the parts while the blocks are fused
            for (a, b), (th, va) in zip(parts, waits(client.gather, angle_f)):
                theta[a:b], valid[a:b] = th, va
            means = [m for _, m in sorted((m for m in waits(client.gather, means_f)
                                           if m is not None), key=operator.itemgetter(0))]
            if not means:  # no peaks: the (empty) cloud of the whole
                return points_block(sysm, {k: v for k, v in peaks.items()
                                            if k != "background_by_step"},
                                    [(0, 0, PeakCounts())], 0, st, acc.n_per_step, table)
            make_points.nbytes = sum(_nbytes(m) for m in means)
            make_points.blocks = len(means)
            # the depth edges look at row neighbours across blocks: made here, on
            # the joined means (milliseconds)
            return cloud_of_means(means, st)

        def count_candidates(cands):
            # the matched filter's candidates, counted on the workers (their stores or
            # their shots) and summed there: the client gets one PeakCounts.  One pass
            # counts them over windows widened to hold any peak they may confirm
            # (matched.confirm: centre within the candidate's steps, ± 1.5 footprints
            # more) together with the first stage's peaks: the candidates' own counts,
            # the first stage's and the confirmed ones' are filtered from it (exact)
            first = shared.get("first")
            if first is None:  # pragma: no cover - detect always runs first
                return waits(pass2_sum(_scatter_one(client, cands)).result)
            both = with_widened_candidates(first, cands, S)
            # one pass per part; ``both`` (a few numbers per window) travels with the
            # tasks, not scattered first (a scatter is a round trip of its own)
            shared["both_f"] = pass2_parts(both)
            shared["cands"] = cands
            # futures of counts to sum: they stay on the workers, score_cands reads them
            return selected_parts(shared["both_f"], candidate_selection(len(first), cands))

        def score_cands(cands, cc_f):
            # the matched filter's search per candidate (a pixel's whole scan: the
            # costly part of the stage) in blocks on the workers, next to the counts;
            # the client joins a few numbers per candidate and runs the support test
            from mems_stereo.pipeline.matched import candidates_block, join_scores

            C = len(cands)
            if C == 0:
                return None
            edges = shot_ranges(C, min(C, n_w * SCORE_BLOCKS_PER_WORKER))
            parts_cc = cc_f if isinstance(cc_f, list) else [cc_f]
            split_f = client.submit(_split_candidates_of_sum, edges, S, n_codes, *parts_cc,
                                    pure=False)
            # (hash=False: the fusion scatters the same array later; a content-hashed
            # key released here would be lost to it)
            nps_f = client.scatter(acc.n_per_step, broadcast=True, hash=False)
            addr = _worker_addresses(client)
            futs = [client.submit(_score_candidates_block, sysm,
                                  *candidates_block(cands, cands.n_windows, a, b),
                                  client.submit(operator.getitem, split_f, i, pure=False),
                                  table_f, nps_f, st, cands.width, pure=False,
                                  workers=[addr[i % len(addr)]] if addr else None,
                                  allow_other_workers=True)
                    for i, (a, b) in enumerate(edges)]
            return join_scores(waits(client.gather, futs))

        res = finish_processing(path, sysm, header, theta, valid, acc, st, timings,
                                count_peaks=count_peaks, make_points=make_points, table=table,
                                count_candidates=count_candidates, detect=detect,
                                score_candidates=score_cands)
        t_end = time.perf_counter()
        c_end = time.process_time()
        m_end = time.thread_time()
    t = res.timings
    # the client's serial work: everything but waiting on its workers (header and
    # angles, table rows' indices, scatters, the peak detector, joining the blocks)
    t["client_serial"] = timings["read_header"] + (t_end - t_run) - waits.seconds
    t["client_wait"] = waits.seconds
    t["client_waits"] = float(waits.count)  # round trips: the client blocked on results
    # CPU seconds of the client process over the run (all its threads: the serial
    # work above plus Dask's communication), the figure to compare on a shared machine
    t["client_cpu"] = c_end - c_all
    t["client_main_cpu"] = m_end - m_all  # this thread alone: the serial work proper
    t["client_bytes"] = float(nbytes + getattr(make_points, "nbytes", 0)
                              + getattr(detect, "nbytes", 0))
    t["parts"] = float(len(parts))
    t["peak_blocks"] = float(getattr(make_points, "blocks", 0))
    return res


def _part_angles(path, system, crossings, start, stop, table):
    """``((theta, valid), missing)`` of shots [start, stop): their scan angles
    (:func:`~mems_stereo.pipeline.angles.shot_angles` of the part's shot times, read
    here, with the recording's validated zero crossings ``crossings``: the same
    values as over the whole, the arithmetic being elementwise) and the rows of
    ``table`` they need that it does not hold (none asked for: ``table`` None)."""
    from mems_stereo.io import hdf5 as h5
    from mems_stereo.io.recording import RecordingHeader

    with h5.open_h5(path) as f:
        t = np.asarray(f["/shots/time"][start:stop], np.float64)
    zc, rising = crossings
    theta, valid = shot_angles(RecordingHeader(system, t, zc, rising, (stop - start,),
                                               str(path)), system)
    missing = (np.zeros(0, np.int64) if table is None
               else table.missing(table.rows(theta, valid)))
    return (theta, valid), missing


def _pass1_part(path, system, angles, settings, start, stop, table, edges):
    """Pass 1 of shots [start, stop): ``(SignalStore or None, slice_0, ...)``, its
    accumulation cut into one slice per block of pixels ``(p0, p1)`` of ``edges``
    (:func:`_pixel_slices`)."""
    theta, valid = angles
    P = system.receiver.width * system.receiver.height
    store = (SignalStore() if (stop - start) * P >= COMPILE_SLOTS
             and rereading_decompresses(path) else None)
    acc = accumulate_range(path, system, theta, valid, settings, start, stop, table=table,
                           angle_offset=start, signal_store=store)
    return (store if store is not None and store.complete else None,
            *_pixel_slices(acc, edges))


def _scatter_one(client, obj):
    """One future of ``obj`` on every worker (a dict scattered directly becomes one
    future per value, keyed by the dict's keys: two dicts of the same fields would
    share their keys)."""
    return client.scatter([obj], broadcast=True)[0]


def _without_angle(acc):
    """``acc`` without its (P, S) ``hist_angle`` (an empty (P, 0) array): what the client
    gathers of pass 1 (the peak detector's blocks read the full one on the workers)."""
    import dataclasses

    return dataclasses.replace(acc, hist_angle=np.zeros((acc.hist_angle.shape[0], 0),
                                                        acc.hist_angle.dtype))


def _pixel_slices(acc, edges):
    """Per block ``(p0, p1)`` of ``edges``: ``acc`` of those pixels alone (its count
    arrays' rows p0..p1−1, copied; the per-shot sums as they are)."""
    import dataclasses

    return [dataclasses.replace(acc, hist_raw=acc.hist_raw[p0:p1].copy(),
                                hist_signal=acc.hist_signal[p0:p1].copy(),
                                hist_angle=acc.hist_angle[p0:p1].copy()) for p0, p1 in edges]


def _block_rows(*slices):
    """The parts' slices of one block of pixels summed (exact integers: the rows of the
    whole's sum): ``((signal, noise, angle, n_per_step), the sum without its per-angle
    counts)`` — the int64 code histograms (codes 1..n_bins) and the signal detections
    per angle step for :func:`_scores_block`, and what the client gathers."""
    acc = _sum(*slices)
    raw = acc.hist_raw[:, 1:].astype(np.int64)
    sig = acc.hist_signal[:, 1:].astype(np.int64)
    return (sig, raw - sig, acc.hist_angle, acc.n_per_step), _without_angle(acc)


def _joined_pixel_blocks(blocks):
    """The sums without per-angle counts of consecutive blocks of pixels joined into the
    whole sensor's (the blocks' per-shot sums are the same: each summed every part)."""
    import dataclasses

    first = blocks[0]
    return dataclasses.replace(
        first, hist_raw=np.concatenate([b.hist_raw for b in blocks]),
        hist_signal=np.concatenate([b.hist_signal for b in blocks]),
        hist_angle=np.zeros((sum(b.hist_angle.shape[0] for b in blocks), 0),
                            first.hist_angle.dtype))


def _scores_block(block, system, settings, table, p0, p1):
    """:class:`~mems_stereo.pipeline.peaks.PeakScores` of pixels p0..p1−1 from their
    :func:`_block_rows` (stays on its worker for
    :func:`~mems_stereo.pipeline.peaks.peaks_of_scores`)."""
    sig, noise, angle, n_per_step = block[0]
    return peak_scores(system, sig, noise, angle, n_per_step, table, settings,
                       np.arange(p0, p1))


def _score_candidates_block(system, cands, n_windows, counts, table, n_per_step, settings,
                            width):
    """:func:`~mems_stereo.pipeline.matched.score_candidates` of a block of candidates."""
    from mems_stereo.pipeline.matched import score_candidates

    return score_candidates(system, cands, counts, table, n_per_step, settings, width,
                            n_windows)


def _support_inputs(scores):
    """What the client needs of a block's scores: ``(keep, cnt, thr_iso, log_range, rate)``."""
    return (*scores.support_inputs(), scores.rate)


def _pass2_part(path, system, angles, settings, peaks, start, stop, table, store=None):
    """Pass 2 of shots [start, stop): from the part's stored signal detections, else
    reading its shots again."""
    if store is not None:
        return peak_counts_from_store(store, system, peaks, table.n_steps)
    theta, valid = angles
    return peak_counts_range(path, system, theta, valid, settings, peaks, start, stop,
                             table=table, angle_offset=start)


def _block_work(blocks, n_steps: int, n_codes: int) -> list[float]:
    """The fusion's work of each block of :func:`split_peak_counts` (its entries,
    :func:`~mems_stereo.pipeline.run.fusion_work`)."""
    return [float(fusion_work(c, q1 - q0, n_steps, n_codes).sum()) for q0, q1, c in blocks]


def deal_blocks(work, workers: Sequence, most: int | None = None) -> list:
    """The worker of each block: the blocks by decreasing ``work``, each to the worker
    with the least work so far (longest processing time first) among those holding
    fewer than ``most`` blocks (None: no limit); None for every block when
    ``workers`` is empty."""
    if not workers:
        return [None] * len(work)
    if most is not None and most * len(workers) < len(work):
        raise OptionError(f"{len(work)} blocks do not fit {len(workers)} workers x {most}",
                          field="most")
    load = dict.fromkeys(workers, 0.0)
    held = dict.fromkeys(workers, 0)
    owner: list = [None] * len(work)
    for i in sorted(range(len(work)), key=lambda i: -work[i]):
        w = min((w for w in load if most is None or held[w] < most), key=load.get)
        owner[i] = w
        load[w] += work[i]
        held[w] += 1
    return owner


def block_slots(work, n_workers: int, per_worker: int) -> list[int]:
    """(n_workers * per_worker,) the block each slot fuses (-1: none), slot s on worker
    s mod ``n_workers``: the blocks dealt by :func:`deal_blocks` (at most
    ``per_worker`` each), a worker's blocks in its slots in block order."""
    owner = deal_blocks(work, list(range(n_workers)), per_worker)
    slots = [-1] * (n_workers * per_worker)
    used = [0] * n_workers
    for b, w in enumerate(owner):
        slots[w + n_workers * used[w]] = b
        used[w] += 1
    return slots


def _means_of_slot(system, peaks, split, s, settings, n_per_step, table):
    """``(block, means)`` of the block in slot ``s`` of ``split`` (:func:`_split_peaks_of_sum`;
    :func:`means_block`), None for an empty slot."""
    blocks, slots = split
    if s >= len(slots) or slots[s] < 0:
        return None
    return slots[s], means_block(system, peaks, blocks, slots[s], settings, n_per_step, table)


def _nbytes(means) -> int:
    return sum(v.nbytes for v in vars(means).values() if isinstance(v, np.ndarray)) + sum(
        a.nbytes for t in (means.stereo, means.tof) for a in t)
