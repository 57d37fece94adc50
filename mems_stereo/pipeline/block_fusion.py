"""The fusion in blocks of peaks: bounded memory in one process, one task each on Dask.

A peak's sums are its own (peak, step, code) entries' alone, so the fusion can run
over blocks of peaks and the blocks be joined, bit for bit the whole's:

* :func:`fuse_in_blocks` / :func:`fused_sums` — one process, blocks of at most
  :data:`FUSE_ENTRIES` entries (the fusion's temporaries bounded by the block);
* :func:`means_block` + :func:`cloud_of_means` — the Dask runner's form: each block's
  peak means on a worker, no halo, joined on the client, where the cloud's depth
  edges are made;
* :func:`points_block` + :func:`join_clouds` — each block's cloud with a halo of its
  row neighbours (the depth edges look across blocks).

Blocks are cut at multiples of ``FP_BLOCK`` peaks (:func:`peak_blocks`), so the
first-photon step groups every peak as the whole run does, and balanced by the
fusion's work per peak (:func:`fusion_work`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import ShapeError
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.first_photon_correction import FP_BLOCK
from mems_stereo.pipeline.fusion import (
    accumulator_for_peaks,
    consistent_points,
    peak_sums_from_counts,
    points_from_counts,
)
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.pass2 import PeakCounts
from mems_stereo.pipeline.peak_means import PeakMeans
from mems_stereo.pipeline.peak_table import Peaks
from mems_stereo.pipeline.settings import Settings

#: most (peak, step, code) entries fused at once by :func:`fuse_in_blocks`: the fusion's
#: temporaries grow with the entries of a block, its CPU time does not shrink with
#: larger blocks
FUSE_ENTRIES = 1 << 16


@dataclass(frozen=True, slots=True)
class PeakBlock:
    """The peaks ``start..stop−1`` of a run and their pass-2 counts.

    counts : :class:`~mems_stereo.pipeline.pass2.PeakCounts` of those peaks alone,
        renumbered from 0 (peak ``start`` is peak 0 of the keys).
    """

    start: int
    stop: int
    counts: PeakCounts


@dataclass(frozen=True, slots=True)
class HaloBlock:
    """The peaks to fuse for one block: its own and a halo of row neighbours.

    peaks : (Q',) int64, sorted indices into the run's peaks.
    counts : their :class:`~mems_stereo.pipeline.pass2.PeakCounts`, renumbered 0..Q'−1.
    own : (a, b), the local range of the block's own peaks within ``peaks``.
    """

    peaks: np.ndarray
    counts: PeakCounts
    own: tuple[int, int]


def fuse_in_blocks(system, peaks: Peaks, counts: PeakCounts, settings: Settings, n_per_step,
                   table: IntervalTable, max_entries: int | None = None) -> PointCloud:
    """:func:`~mems_stereo.pipeline.fusion.points_from_counts` over blocks of peaks of at
    most about ``max_entries`` distinct (peak, step, code) entries each
    (:func:`fused_sums`): the cloud of the joined accumulator is the whole's bit for bit,
    with the fusion's per-entry arrays bounded by the block
    instead of growing with the recording's distinct entries (default
    :data:`FUSE_ENTRIES`)."""
    cap = FUSE_ENTRIES if max_entries is None else max_entries
    if counts.keys.size <= cap:
        return points_from_counts(system, peaks, counts, settings, shots_per_step=n_per_step,
                                  table=table)
    acc = fused_sums(system, peaks, counts, settings, n_per_step, table, cap)
    return consistent_points(acc.cloud(settings.min_counts), settings.confidence)


def fused_sums(system, peaks: Peaks, counts: PeakCounts, settings: Settings, n_per_step,
               table: IntervalTable, max_entries: int | None = None):
    """The :class:`~mems_stereo.pipeline.fusion.PeakAccumulator` of ``peaks`` after both
    sub-passes over ``counts``, computed over blocks of peaks of at most about
    ``max_entries`` distinct entries each (default :data:`FUSE_ENTRIES`; cut at
    multiples of ``FP_BLOCK`` peaks) and joined
    (:meth:`~mems_stereo.pipeline.fusion.PeakAccumulator.joined`): a peak's sums are its
    entries' alone, so the result is the one accumulator of every entry, bit for bit.
    The fusion's cost per entry grows with the block (its temporaries), so the Dask
    runner's blocks of peaks are cut the same way on their workers."""
    cap = FUSE_ENTRIES if max_entries is None else max_entries
    light = peaks.light()
    n_blocks = max(1, math.ceil(counts.keys.size / max(1, int(cap))))
    if n_blocks == 1:
        return peak_sums_from_counts(system, light, counts, settings, n_per_step, table)
    # each block's sums, joined: no halo of neighbours to fuse twice (the cloud's depth
    # edges are made on the joined sums)
    blocks = split_peak_counts(counts, len(light), table.n_steps, system.tdc.n_bins + 1,
                               n_blocks)
    parts = [peak_sums_from_counts(system, light.take(slice(b.start, b.stop)), b.counts,
                                   settings, n_per_step, table) for b in blocks]
    return accumulator_for_peaks(system, light, settings, n_per_step, table).joined(parts)


def block_with_halo(system, peaks: Peaks, blocks: Sequence[PeakBlock], i: int,
                    n_steps: int) -> HaloBlock:
    """Peaks to fuse for block ``i``: its own and a halo.

    The fusion of a peak depends on its row neighbours (column ± 1: the depth
    edges of :meth:`PeakAccumulator.cloud`), so the halo holds every peak of a
    pixel beside one of the block's; it is widened to whole groups of
    ``FP_BLOCK`` peaks by index, so the first-photon step groups every peak as
    the whole run does and the halo's points are the whole's, bit for bit.
    """
    q0, q1 = blocks[i].start, blocks[i].stop
    rows = np.asarray(peaks.row, np.int64)
    cols = np.asarray(peaks.col, np.int64)
    Q = rows.size
    W = int(system.receiver.width)
    pix = rows * (W + 2) + cols  # a padded row: column −1 and W belong to no pixel
    mine = np.unique(pix[q0:q1])
    halo = np.flatnonzero(np.isin(pix, np.concatenate([mine - 1, mine + 1])))
    groups = np.unique(np.concatenate([np.arange(q0, q1), halo]) // FP_BLOCK)
    sel = (groups[:, None] * FP_BLOCK + np.arange(FP_BLOCK)[None, :]).ravel()
    sel = sel[sel < Q]
    span = np.int64(n_steps) * np.int64(system.tdc.n_bins + 1)  # keys of split_peak_counts
    keys, vals = [], []
    for b in blocks:
        c = b.counts
        if b.stop <= b.start or c.keys.size == 0 or not np.any((sel >= b.start)
                                                               & (sel < b.stop)):
            continue
        gq = c.keys // span + b.start
        m = np.isin(gq, sel)
        keys.append(np.searchsorted(sel, gq[m]) * span + c.keys[m] % span)
        vals.append(c.counts[m])
    counts = (PeakCounts(np.concatenate(keys), np.concatenate(vals)) if keys
              else PeakCounts())
    own = (int(np.searchsorted(sel, q0)), int(np.searchsorted(sel, q1)))
    return HaloBlock(sel, counts, own)


def points_block(system, peaks: Peaks, blocks: Sequence[PeakBlock], i: int,
                 settings: Settings, n_per_step, table: IntervalTable) -> PointCloud:
    """The cloud of the peaks of block ``i`` of ``blocks`` (:func:`split_peak_counts`),
    fused with the halo of :func:`block_with_halo`: the blocks' clouds joined are the
    whole's, bit for bit."""
    halo = block_with_halo(system, peaks, blocks, i, table.n_steps)
    return points_from_counts(system, peaks.take(halo.peaks), halo.counts, settings,
                              shots_per_step=n_per_step, table=table, own=halo.own)


def means_block(system, peaks: Peaks, blocks: Sequence[PeakBlock], i: int,
                settings: Settings, n_per_step, table: IntervalTable) -> PeakMeans:
    """The :class:`~mems_stereo.pipeline.peak_means.PeakMeans` of the peaks of block ``i``
    of ``blocks`` (:func:`split_peak_counts`), no halo: the blocks' means joined
    (``PeakMeans.concat``) give the whole's cloud, bit for bit (:func:`cloud_of_means`).
    A block of more than :data:`FUSE_ENTRIES` entries is fused in sub-blocks
    (:func:`fused_sums`), as one process does."""
    b = blocks[i]
    return fused_sums(system, peaks.take(slice(b.start, b.stop)), b.counts, settings,
                      n_per_step, table).peak_means()


def cloud_of_means(means: Sequence[PeakMeans], settings: Settings) -> PointCloud:
    """The cloud of the joined means of consecutive peak blocks (consistent points)."""
    return consistent_points(PeakMeans.concat(means).cloud(settings.min_counts),
                             settings.confidence)


def peak_blocks(entries_per_peak, n_blocks: int, unit: int = FP_BLOCK) -> list[tuple[int, int]]:
    """Split the peaks 0..Q into at most ``n_blocks`` contiguous ranges ``(q0, q1)``.

    Cuts only at multiples of ``unit`` (the fusion's first-photon block
    :data:`~mems_stereo.pipeline.first_photon_correction.FP_BLOCK`, so the blocks' clouds
    joined are the whole's, bit for bit), each near an equal share of the fusion's work
    (``entries_per_peak`` (Q,): the peaks' distinct (step, code) entries, plus one).
    """
    e = np.asarray(entries_per_peak, np.float64).ravel()
    Q = e.size
    if Q == 0:
        return []
    cand = np.arange(unit, Q, unit)
    cum = np.concatenate([[0.0], np.cumsum(e + 1.0)])
    chosen = []
    if cand.size and n_blocks > 1:
        targets = cum[-1] * np.arange(1, n_blocks) / n_blocks
        at = np.clip(np.searchsorted(cum[cand], targets), 0, cand.size - 1)
        lower = np.clip(at - 1, 0, cand.size - 1)  # the nearer of the two candidates
        pick = np.where(np.abs(cum[cand[lower]] - targets) < np.abs(cum[cand[at]] - targets),
                        lower, at)
        chosen = cand[pick]
    edges = np.unique(np.concatenate([[0], chosen, [Q]])).astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def split_peak_counts(counts: PeakCounts, n_peaks: int, n_steps: int, n_codes: int,
                      n_blocks: int) -> list[PeakBlock]:
    """The :class:`PeakBlock` of each block of :func:`peak_blocks` (balanced by
    :func:`fusion_work`); keys are sorted by peak, so each block is a slice."""
    span = np.int64(n_steps) * np.int64(n_codes)
    keys = counts.keys
    out = []
    for q0, q1 in peak_blocks(fusion_work(counts, n_peaks, n_steps, n_codes), n_blocks):
        a, b = np.searchsorted(keys, [q0 * span, q1 * span])
        out.append(PeakBlock(q0, q1, PeakCounts(keys[a:b] - q0 * span,
                                                counts.counts[a:b].copy())))
    return out


def fusion_work(counts: PeakCounts, n_peaks: int, n_steps: int, n_codes: int) -> np.ndarray:
    """(Q,) int64, the fusion's entries per peak: its distinct (step, code) keys plus
    ``BACKGROUND_SEGMENTS`` negative-weight entries per distinct step (the expected
    background, :func:`~mems_stereo.pipeline.window_background.window_background`);
    what :func:`split_peak_counts` balances its blocks by."""
    from mems_stereo.pipeline.window_background import BACKGROUND_SEGMENTS

    keys = counts.keys
    if keys.size == 0:
        return np.zeros(n_peaks, np.int64)
    q = keys // (np.int64(n_steps) * np.int64(n_codes))
    g = keys // np.int64(n_codes)  # peak · S + step, sorted with the keys
    new_step = np.ones(g.size, bool)
    new_step[1:] = g[1:] != g[:-1]
    return (np.bincount(q, minlength=n_peaks)
            + BACKGROUND_SEGMENTS * np.bincount(q[new_step], minlength=n_peaks))


def join_clouds(clouds: Sequence[PointCloud]) -> PointCloud:
    """The clouds of consecutive peak blocks as one, attributes in the order of the
    whole run's.  A block none of whose peaks has an inlier band carries no
    first-photon attributes (``tof_delay``, ``signal_photons``); the whole run
    gives its peaks NaN there, and so does this."""
    full = max(clouds, key=lambda c: len(c.attributes))
    attrs = {}
    for k, v in full.attributes.items():
        parts = []
        for c in clouds:
            if k in c.attributes:
                parts.append(c.attributes[k])
            elif v.dtype.kind == "f":
                parts.append(np.full(len(c), np.nan, v.dtype))
            else:  # pragma: no cover - only the float first-photon attributes are optional
                raise ShapeError(f"attribute {k!r} missing from a peak block")
        attrs[k] = np.concatenate(parts)
    for c in clouds:
        extra = set(c.attributes) - set(full.attributes)
        if extra:  # pragma: no cover
            raise ShapeError(f"peak blocks with different attributes: {sorted(extra)}")
    return PointCloud(np.concatenate([c.points for c in clouds]), attrs)
