"""The client's steps of ``process_split``: each submits one stage of the chain to the
workers (the same stage functions as one process, :mod:`~mems_stereo.pipeline.dask_tasks`)
and returns futures, or gathers the little the next step needs on the client.

What keeps the client's serial share small:

* the interval table of a run is built once: its rows are computed by the workers in
  parallel (:func:`fill_table`) and scattered to every worker once;
* each part computes its own shots' angles on its worker and keeps them there;
* pass 1 is reduced and scattered by blocks of pixels on the workers (each part
  slices its rows of each block where it lies, each block's slices are summed on the
  block's worker, where the peak detector's per-pixel stage then runs), so the client
  receives one pass-1 result without its (P, S) per-angle counts;
* each part keeps its signal detections on its worker
  (:class:`~mems_stereo.pipeline.signal_store.SignalStore`) and counts pass 2 from
  them: one pass for the first stage's peaks and the matched filter's candidates
  together, each set's counts selected from it where they lie;
* pass 2's sum stays on the workers: one task sums and splits it by blocks of peaks
  and deals them to the workers' slots, and each slot fuses its block there up to the
  peaks' means; the client joins the means and makes the cloud.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass

import numpy as np

from mems_stereo.io.recording import RecordingHeader
from mems_stereo.model.system import System
from mems_stereo.pipeline.block_fusion import PeakBlock, cloud_of_means, points_block
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.dask_plan import (
    BLOCKS_PER_WORKER,
    PARTS_PER_WORKER,
    PEAK_BLOCKS_PER_WORKER,
    SCORE_BLOCKS_PER_WORKER,
    shot_ranges,
)
from mems_stereo.pipeline.dask_reduce import FAN_IN, tree_reduce, tree_sum
from mems_stereo.pipeline.dask_setup import (
    ClientWaits,
    n_workers_of,
    on_worker,
    scatter_one,
    worker_addresses,
)
from mems_stereo.pipeline.dask_tasks import (
    ShotPart,
    block_rows,
    block_summary,
    joined_pixel_blocks,
    means_nbytes,
    means_of_slot,
    part_angles,
    part_angles_only,
    part_missing,
    part_slice,
    part_store,
    pass1_part,
    pass2_part,
    score_candidates_block,
    scores_block,
    split_candidates_of_sum,
    split_peaks_of_sum,
    support_inputs,
    table_rows,
)
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.matched import CandidateScores, candidates_block, join_scores
from mems_stereo.pipeline.pass1 import RangeAccumulation
from mems_stereo.pipeline.pass2 import (
    CountSelection,
    PeakCounts,
    candidate_selection,
    merged_selection,
    select_counts,
    with_widened_candidates,
)
from mems_stereo.pipeline.peak_support import SupportInputs
from mems_stereo.pipeline.peak_table import Candidates, Peaks
from mems_stereo.pipeline.peaks import concat_peaks, peaks_of_scores
from mems_stereo.pipeline.run import candidates_of
from mems_stereo.pipeline.settings import Settings


@dataclass(frozen=True, slots=True)
class SplitRun:
    """What the client's steps share: the client, the run's system, settings and
    interval table (``table`` here, ``table_f`` its future on every worker), the parts
    and, per part, the future of its shots' ``(theta, valid)`` on its worker."""

    client: object
    system: System
    settings: Settings
    table: IntervalTable
    table_f: object
    parts: tuple[ShotPart, ...]
    angles: tuple
    waits: ClientWaits

    @property
    def n_steps(self) -> int:
        """S, the interval table's angle steps."""
        return self.table.n_steps

    @property
    def n_codes(self) -> int:
        """Codes of a pass-2 key (n_bins + 1)."""
        return self.system.tdc.n_bins + 1


@dataclass(frozen=True, slots=True)
class Pass1OnWorkers:
    """Pass 1 of a split run.

    acc : the whole's sum without its per-angle counts (on the client).
    stores : per part, the future of its signal store (None: its shots are read again).
    scores : per block of pixels, the future of its peak scores, on the block's worker.
    support : per block, the future of its :class:`SupportInputs`.
    edges : the blocks of pixels, ``(p0, p1)`` each.
    """

    acc: RangeAccumulation
    stores: list
    scores: list
    support: list
    edges: list[tuple[int, int]]


@dataclass(frozen=True, slots=True)
class FoundPeaks:
    """The first stage's peaks (with their candidates), the (H, W) float64 background
    rate per pixel in Hz, and the bytes the client received for them."""

    peaks: Peaks
    background: np.ndarray
    nbytes: int


@dataclass(frozen=True, slots=True)
class CandidatesOnWorkers:
    """The matched filter's candidates and, per group of parts, the futures of their
    counts (``counts``) and of the joint count of the first stage's peaks with the
    candidates' widened windows (``joint``, per part)."""

    candidates: Candidates
    joint: list
    counts: list


@dataclass(frozen=True, slots=True)
class CountsOnWorkers:
    """Pass 2 of a split run: the light peaks on every worker (``peaks_f``) and the
    futures of their counts to sum (``total``), each on a worker."""

    peaks_f: object
    total: list


@dataclass(frozen=True, slots=True)
class FusedCloud:
    """The cloud of a split run, the blocks of peaks fused on the workers and the bytes
    of their means that the client received."""

    cloud: PointCloud
    n_blocks: int
    nbytes: int


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
    blocks = [b for b in np.array_split(need, n_workers_of(client)) if b.size]
    futs = client.map(table_rows, [table.system] * len(blocks), [st] * len(blocks), blocks,
                      pure=False)
    got = client.gather(futs) if waits is None else waits(client.gather, futs)
    for b, (lo, hi) in zip(blocks, got):
        table.put_rows(b, lo, hi)
    table.save_cache()
    return table


def start_parts(client, path: str, header: RecordingHeader, system: System,
                settings: Settings, table: IntervalTable, n_parts: int | None,
                waits: ClientWaits) -> SplitRun:
    """The parts of the run, each computing its shots' angles on a worker (the same
    elementwise arithmetic as over the whole; the client computes and sends none); the
    table's rows they need and lack are filled on the workers first (:func:`fill_table`;
    none asked for where the table holds every row: no round trip)."""
    n_shots = header.shape[0]
    parts = tuple(ShotPart(path, a, b) for a, b in shot_ranges(
        n_shots, n_parts or n_workers_of(client) * PARTS_PER_WORKER))
    table_f = client.scatter(table, broadcast=True)
    zc_f = scatter_one(client, (header.zero_crossings, header.rising))
    complete = bool(table.filled.all())
    ang_missing = [client.submit(part_angles, p, system, zc_f, None if complete else table_f,
                                 pure=False) for p in parts]
    angle_f = tuple(client.submit(part_angles_only, f, pure=False) for f in ang_missing)
    if not complete:
        need = np.unique(np.concatenate(waits(client.gather, [
            client.submit(part_missing, f, pure=False) for f in ang_missing])))
        if need.size:
            fill_table(client, table, need, settings=settings, waits=waits)
            table_f = client.scatter(table, broadcast=True)
    return SplitRun(client, system, settings, table, table_f, parts, angle_f, waits)


def pass1_on_workers(run: SplitRun) -> Pass1OnWorkers:
    """Pass 1 per part, reduced and scattered by blocks of pixels on the workers, the
    peak detector's per-pixel stage submitted on each block where it lies; the client
    gathers the sum without its per-angle counts."""
    client, sysm = run.client, run.system
    P = sysm.receiver.width * sysm.receiver.height
    edges = shot_ranges(P, min(P, n_workers_of(client) * PEAK_BLOCKS_PER_WORKER))
    addr = worker_addresses(client)
    parts = [client.submit(pass1_part, part, sysm, ang, run.settings, run.table_f, edges,
                           pure=False) for ang, part in zip(run.angles, run.parts)]
    stores = [client.submit(part_store, f, pure=False) for f in parts]
    blocks = [client.submit(block_rows, *[client.submit(part_slice, f, i, pure=False)
                                          for f in parts], pure=False, **on_worker(addr, i))
              for i in range(len(edges))]
    scores = [client.submit(scores_block, b, sysm, run.settings, run.table_f, a, z,
                            pure=False, **on_worker(addr, i))
              for i, (b, (a, z)) in enumerate(zip(blocks, edges))]
    support = [client.submit(support_inputs, f, pure=False) for f in scores]
    acc = joined_pixel_blocks(run.waits(client.gather, [
        client.submit(block_summary, b, pure=False) for b in blocks]))
    return Pass1OnWorkers(acc, stores, scores, support, edges)


def detect_on_workers(run: SplitRun, pass1: Pass1OnWorkers) -> FoundPeaks:
    """The peak detector: the client joins the few numbers per pixel that the neighbour
    support needs, then each block of pixels makes its peaks where its scores lie (the
    same as :func:`~mems_stereo.pipeline.peaks.find_peaks` on the whole, bit for bit)."""
    client, sysm = run.client, run.system
    sup = run.waits(client.gather, pass1.support)
    joined = SupportInputs.concat(sup)
    keep = joined.supported(sysm.receiver.width)
    parts = run.waits(client.gather, [
        client.submit(peaks_of_scores, sysm, f, keep[a:z], pass1.acc.n_per_step, run.table_f,
                      run.settings, pure=False) for f, (a, z) in zip(pass1.scores, pass1.edges)])
    return FoundPeaks(concat_peaks(parts),
                      joined.rate.reshape(sysm.receiver.height, sysm.receiver.width),
                      sum(s.nbytes for s in sup))


def pass2_parts(run: SplitRun, peaks, stores: list) -> list:
    """Per part, the future of its pass 2 of ``peaks`` (its store or its shots), on the
    part's worker."""
    return [run.client.submit(pass2_part, part, run.system, ang, run.settings, peaks,
                              run.table_f, store, pure=False)
            for part, ang, store in zip(run.parts, run.angles, stores)]


def selected_parts(run: SplitRun, parts_f: list, sel: CountSelection) -> list:
    """:func:`~mems_stereo.pipeline.pass2.select_counts` of each part where it lies, the
    selections summed in a tree down to :data:`FAN_IN` futures (the task that reads them
    sums them: the selection of the sum, each key's count its parts' sum)."""
    return tree_reduce(run.client, [run.client.submit(select_counts, f, sel, run.n_steps,
                                                      run.n_codes, pure=False)
                                    for f in parts_f], FAN_IN)


def count_candidates_on_workers(run: SplitRun, first: Peaks,
                                stores: list) -> CandidatesOnWorkers | None:
    """Pass 2 of the matched filter's candidates (None: none), counted on the workers in
    one pass with the first stage's peaks over windows widened to hold any peak a
    candidate may confirm; the candidates' own counts are selected where they lie."""
    cands = candidates_of(first)
    if cands is None:
        return None
    # ``joint`` (a few numbers per window) travels with the tasks, not scattered first
    # (a scatter is a round trip of its own)
    joint = pass2_parts(run, with_widened_candidates(first, cands, run.n_steps), stores)
    return CandidatesOnWorkers(cands, joint, selected_parts(
        run, joint, candidate_selection(len(first), cands)))


def score_on_workers(run: SplitRun, cc: CandidatesOnWorkers, n_per_step) -> CandidateScores:
    """The matched filter's search per candidate (a pixel's whole scan: the costly part
    of the stage) in blocks on the workers, next to the counts; the client joins a few
    numbers per candidate."""
    client, cands = run.client, cc.candidates
    C = len(cands)
    edges = shot_ranges(C, min(C, n_workers_of(client) * SCORE_BLOCKS_PER_WORKER))
    split_f = client.submit(split_candidates_of_sum, edges, run.n_steps, run.n_codes,
                            *cc.counts, pure=False)
    # (hash=False: the fusion scatters the same array later; a content-hashed key
    # released here would be lost to it)
    nps_f = client.scatter(n_per_step, broadcast=True, hash=False)
    addr = worker_addresses(client)
    futs = [client.submit(score_candidates_block, run.system, candidates_block(cands, a, b),
                          client.submit(operator.getitem, split_f, i, pure=False),
                          run.table_f, nps_f, run.settings, pure=False, **on_worker(addr, i))
            for i, (a, b) in enumerate(edges)]
    return join_scores(run.waits(client.gather, futs))


def count_peaks_on_workers(run: SplitRun, first: Peaks, cc: CandidatesOnWorkers | None,
                           peaks: Peaks, stores: list) -> CountsOnWorkers:
    """Pass 2 of ``peaks``, its counts left on the workers: selected from the joint
    count of the candidates where there is one (each peak's counts its own), else
    counted per part and summed in a tree.  The light peaks go to every worker once
    (the fusion's blocks read them)."""
    if cc is None:
        peaks_f = scatter_one(run.client, peaks.light())
        return CountsOnWorkers(peaks_f, [tree_sum(run.client,
                                                  pass2_parts(run, peaks_f, stores))])
    total = selected_parts(run, cc.joint, merged_selection(first, cc.candidates, peaks,
                                                           run.system.receiver.width))
    # sent while the selections run (a scatter waits for its data to arrive)
    return CountsOnWorkers(scatter_one(run.client, peaks.light()), total)


def submit_fusion(run: SplitRun, counted: CountsOnWorkers, n_peaks: int,
                  n_per_step) -> list:
    """The fusion's futures, one per slot: one task sums the counts, splits them into
    blocks of peaks and deals them to the workers' slots by their work (the largest
    first to the least loaded); each slot's task is pinned to its worker and submitted
    with it, so no round trip comes between (left to itself the scheduler would run
    every block where the counts lie)."""
    client = run.client
    nps_f = client.scatter(n_per_step, broadcast=True)
    addr = worker_addresses(client)
    n_slot_w = max(1, len(addr))
    split_f = client.submit(split_peaks_of_sum, n_peaks, run.n_steps, run.n_codes, n_slot_w,
                            BLOCKS_PER_WORKER, *counted.total, pure=False)
    return [client.submit(means_of_slot, run.system, counted.peaks_f, split_f, i,
                          run.settings, nps_f, run.table_f, pure=False, **on_worker(addr, i))
            for i in range(n_slot_w * BLOCKS_PER_WORKER)]


def gather_angles(run: SplitRun, n_shots: int) -> tuple[np.ndarray, np.ndarray]:
    """``(theta (K,) float64 rad, valid (K,) bool)`` of every shot, from the parts'."""
    theta = np.empty(n_shots, np.float64)
    valid = np.zeros(n_shots, bool)
    for part, (th, va) in zip(run.parts, run.waits(run.client.gather, list(run.angles))):
        theta[part.start:part.stop], valid[part.start:part.stop] = th, va
    return theta, valid


def join_fusion(run: SplitRun, means_f: list, peaks: Peaks, n_per_step) -> FusedCloud:
    """The cloud of the blocks' means (its depth edges look at row neighbours across
    blocks: made here, on the joined means)."""
    got = [m for m in run.waits(run.client.gather, means_f) if m is not None]
    means = [m.means for m in sorted(got, key=operator.attrgetter("block"))]
    if not means:  # no peaks: the (empty) cloud of the whole
        return FusedCloud(points_block(run.system, peaks, [PeakBlock(0, 0, PeakCounts())], 0,
                                       run.settings, n_per_step, run.table), 0, 0)
    return FusedCloud(cloud_of_means(means, run.settings), len(means),
                      sum(means_nbytes(m) for m in means))
