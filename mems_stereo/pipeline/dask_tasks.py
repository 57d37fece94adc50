"""The tasks that a scale-out run's workers execute: each calls the same stage function
as one process does, on a part of the shots, a block of pixels, of candidates or of
peaks.  What they return is typed (small frozen dataclasses) and stays on the workers
unless the client gathers it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mems_stereo.model.system import System
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.block_fusion import PeakBlock, means_block, split_peak_counts
from mems_stereo.pipeline.dask_plan import block_slots, block_work
from mems_stereo.pipeline.dask_reduce import sum_parts
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.matched import (
    CandidateScores,
    score_candidates,
    split_candidate_counts,
)
from mems_stereo.pipeline.pass1 import COMPILE_SLOTS, RangeAccumulation, accumulate_range
from mems_stereo.pipeline.pass2 import PeakCounts, peak_counts_range
from mems_stereo.pipeline.peak_means import PeakMeans
from mems_stereo.pipeline.peak_table import Candidates, Peaks
from mems_stereo.pipeline.peaks import PeakScores, peak_scores
from mems_stereo.pipeline.run import process_recording
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange
from mems_stereo.pipeline.signal_store import (
    SignalStore,
    peak_counts_from_store,
    rereading_decompresses,
)


@dataclass(frozen=True, slots=True)
class ShotPart:
    """One part of a split recording: the file and its shots ``[start, stop)``."""

    path: str
    start: int
    stop: int


@dataclass(frozen=True, slots=True)
class PartAngles:
    """A part's scan angles and the interval table's rows they need that it lacks.

    angles : ``(theta (n,) float64 rad, valid (n,) bool)`` of the part's shots.
    missing : (M,) int64 rows of the table (empty where none was asked for).
    """

    angles: tuple[np.ndarray, np.ndarray]
    missing: np.ndarray


@dataclass(frozen=True, slots=True)
class Pass1Part:
    """Pass 1 of a part: its signal store (None: pass 2 reads the shots again) and its
    :class:`RangeAccumulation` cut into one slice per block of pixels."""

    store: SignalStore | None
    slices: tuple[RangeAccumulation, ...]


@dataclass(frozen=True, slots=True)
class PixelBlock:
    """The parts' pass 1 summed over one block of pixels (Pb pixels).

    signal, noise : (Pb, n_bins) int64 code histograms (codes 1..n_bins).
    angle : (Pb, S) signal detections per angle step.  n_per_step : (S,) valid shots
    per step.  summary : the sum without its per-angle counts (what the client gathers).
    """

    signal: np.ndarray
    noise: np.ndarray
    angle: np.ndarray
    n_per_step: np.ndarray
    summary: RangeAccumulation


@dataclass(frozen=True, slots=True)
class SlotPlan:
    """The fusion's blocks of peaks and the block each slot fuses (-1: none; slot s on
    worker s mod the workers, :func:`~mems_stereo.pipeline.dask_plan.block_slots`)."""

    blocks: list[PeakBlock]
    slots: list[int]


@dataclass(frozen=True, slots=True)
class SlotMeans:
    """The peak means of block ``block`` (fused in one slot)."""

    block: int
    means: PeakMeans


def table_rows(system: System, settings: Settings, rows):
    """Rows ``rows`` of the run's interval table (:meth:`IntervalTable.compute_rows`)."""
    return IntervalTable.for_settings(system, settings).compute_rows(rows)


def process_task(path, system, settings, table) -> object:
    """One recording of ``process_many``: :func:`process_recording` with the run's table."""
    return process_recording(path, system=system, settings=settings, table=table)


def part_angles(part: ShotPart, system: System, crossings, table) -> PartAngles:
    """The part's scan angles (:func:`~mems_stereo.pipeline.angles.shot_angles` of its
    shot times, read here, with the recording's validated zero crossings
    ``(zero_crossings, rising)``: the same values as over the whole, the arithmetic
    being elementwise) and the rows of ``table`` they need that it does not hold (none
    asked for: ``table`` None)."""
    from mems_stereo.io import hdf5 as h5
    from mems_stereo.io.recording import RecordingHeader

    with h5.open_h5(part.path) as f:
        t = np.asarray(f["/shots/time"][part.start:part.stop], np.float64)
    zc, rising = crossings
    theta, valid = shot_angles(RecordingHeader(system, t, zc, rising,
                                               (part.stop - part.start,), part.path), system)
    missing = (np.zeros(0, np.int64) if table is None
               else table.missing(table.rows(theta, valid)))
    return PartAngles((theta, valid), missing)


def part_angles_only(pa: PartAngles) -> tuple[np.ndarray, np.ndarray]:
    """``pa.angles`` (a task of its own, so that the part's passes read them there)."""
    return pa.angles


def part_missing(pa: PartAngles) -> np.ndarray:
    """``pa.missing``."""
    return pa.missing


def pass1_part(part: ShotPart, system: System, angles, settings: Settings, table,
               edges: Sequence[tuple[int, int]]) -> Pass1Part:
    """Pass 1 of the part's shots, its accumulation cut into one slice per block of
    pixels ``(p0, p1)`` of ``edges`` (:func:`pixel_slices`)."""
    theta, valid = angles
    P = system.receiver.width * system.receiver.height
    store = (SignalStore() if (part.stop - part.start) * P >= COMPILE_SLOTS
             and rereading_decompresses(part.path) else None)
    acc = accumulate_range(part.path, system,
                           ShotRange(theta, valid, part.start, part.stop, part.start), settings,
                           table=table, signal_store=store)
    return Pass1Part(store if store is not None and store.complete else None,
                     tuple(pixel_slices(acc, edges)))


def part_store(p1: Pass1Part) -> SignalStore | None:
    """``p1.store``."""
    return p1.store


def part_slice(p1: Pass1Part, i: int) -> RangeAccumulation:
    """``p1.slices[i]``."""
    return p1.slices[i]


def pixel_slices(acc: RangeAccumulation, edges) -> list[RangeAccumulation]:
    """Per block ``(p0, p1)`` of ``edges``: ``acc`` of those pixels alone (its count
    arrays' rows p0..p1−1, copied; the per-shot sums as they are)."""
    return [dataclasses.replace(acc, hist_raw=acc.hist_raw[p0:p1].copy(),
                                hist_signal=acc.hist_signal[p0:p1].copy(),
                                hist_angle=acc.hist_angle[p0:p1].copy()) for p0, p1 in edges]


def without_angle(acc: RangeAccumulation) -> RangeAccumulation:
    """``acc`` without its (P, S) ``hist_angle`` (an empty (P, 0) array): what the client
    gathers of pass 1 (the peak detector's blocks read the full one on the workers)."""
    return dataclasses.replace(acc, hist_angle=np.zeros((acc.hist_angle.shape[0], 0),
                                                        acc.hist_angle.dtype))


def block_rows(*slices: RangeAccumulation) -> PixelBlock:
    """The parts' slices of one block of pixels summed (exact integers: the rows of the
    whole's sum)."""
    acc = sum_parts(*slices)
    raw = acc.hist_raw[:, 1:].astype(np.int64)
    sig = acc.hist_signal[:, 1:].astype(np.int64)
    return PixelBlock(sig, raw - sig, acc.hist_angle, acc.n_per_step, without_angle(acc))


def block_summary(block: PixelBlock) -> RangeAccumulation:
    """``block.summary``."""
    return block.summary


def joined_pixel_blocks(blocks: Sequence[RangeAccumulation]) -> RangeAccumulation:
    """The sums without per-angle counts of consecutive blocks of pixels joined into the
    whole sensor's (the blocks' per-shot sums are the same: each summed every part)."""
    first = blocks[0]
    return dataclasses.replace(
        first, hist_raw=np.concatenate([b.hist_raw for b in blocks]),
        hist_signal=np.concatenate([b.hist_signal for b in blocks]),
        hist_angle=np.zeros((sum(b.hist_angle.shape[0] for b in blocks), 0),
                            first.hist_angle.dtype))


def scores_block(block: PixelBlock, system: System, settings: Settings, table,
                 p0: int, p1: int) -> PeakScores:
    """:class:`~mems_stereo.pipeline.peaks.PeakScores` of pixels p0..p1−1 (stays on its
    worker for :func:`~mems_stereo.pipeline.peaks.peaks_of_scores`)."""
    return peak_scores(system, block.signal, block.noise, block.angle, block.n_per_step,
                       table, settings, np.arange(p0, p1))


def support_inputs(scores: PeakScores):
    """What the client needs of a block's scores for the neighbour support."""
    return scores.support_inputs()


def pass2_part(part: ShotPart, system: System, angles, settings: Settings, peaks: Peaks,
               table, store: SignalStore | None = None) -> PeakCounts:
    """Pass 2 of the part's shots: from its stored signal detections, else reading its
    shots again."""
    if store is not None:
        return peak_counts_from_store(store, system, peaks, table.n_steps)
    theta, valid = angles
    return peak_counts_range(part.path, system, ShotRange(theta, valid, part.start, part.stop,
                                                          angle_offset=part.start),
                             settings, peaks, table=table)


def split_candidates_of_sum(edges, n_steps: int, n_codes: int,
                            *parts: PeakCounts) -> list[PeakCounts]:
    """:func:`~mems_stereo.pipeline.matched.split_candidate_counts` of the parts' sum."""
    return split_candidate_counts(sum_parts(*parts), edges, n_steps, n_codes)


def score_candidates_block(system: System, cands: Candidates, counts: PeakCounts, table,
                           n_per_step, settings: Settings) -> CandidateScores:
    """:func:`~mems_stereo.pipeline.matched.score_candidates` of a block of candidates."""
    return score_candidates(system, cands, counts, table, n_per_step, settings)


def split_peaks_of_sum(n_peaks: int, n_steps: int, n_codes: int, n_workers: int,
                       per_worker: int, *parts: PeakCounts) -> SlotPlan:
    """:func:`~mems_stereo.pipeline.block_fusion.split_peak_counts` of the parts' sum in
    at most ``n_workers * per_worker`` blocks, dealt to the slots by the blocks' work
    here, so that the client submits the slots' tasks at once, without waiting for the
    work to come back."""
    blocks = split_peak_counts(sum_parts(*parts), n_peaks, n_steps, n_codes,
                               n_workers * per_worker)
    return SlotPlan(blocks, block_slots(block_work(blocks, n_steps, n_codes), n_workers,
                                        per_worker))


def means_of_slot(system: System, peaks: Peaks, plan: SlotPlan, s: int, settings: Settings,
                  n_per_step, table) -> SlotMeans | None:
    """The means of the block in slot ``s`` of ``plan`` (:func:`means_block`), None for
    an empty slot."""
    if s >= len(plan.slots) or plan.slots[s] < 0:
        return None
    b = plan.slots[s]
    return SlotMeans(b, means_block(system, peaks, plan.blocks, b, settings, n_per_step,
                                    table))


def means_nbytes(means: PeakMeans) -> int:
    """Bytes of a block's means (what the client receives of it)."""
    arrays = (getattr(means, f.name) for f in dataclasses.fields(means))
    return sum(v.nbytes for v in arrays if isinstance(v, np.ndarray)) + sum(
        a.nbytes for t in (means.stereo, means.tof) for a in t)
