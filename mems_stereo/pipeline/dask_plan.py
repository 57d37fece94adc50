"""Planning the parts of a scale-out run: shot ranges, blocks of pixels and of
candidates, and the dealing of the fusion's blocks of peaks to the workers' slots.

Pure functions of sizes and work estimates: no Dask here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mems_stereo.errors import OptionError
from mems_stereo.pipeline.block_fusion import PeakBlock, fusion_work

#: shot ranges of ``process_split`` per worker (default of ``n_parts``): one.  More
#: parts cost each their pass-1 arrays, their tasks on the client and their transfers
PARTS_PER_WORKER = 1

#: blocks of peaks fused per worker (at most: blocks are cut at multiples of
#: ``FP_BLOCK`` peaks), dealt to the workers' slots by their work (:func:`block_slots`)
BLOCKS_PER_WORKER = 4

#: blocks of pixels per worker in which ``process_split`` runs the peak detector
#: (its per-pixel stages; the neighbour support between them on the client)
PEAK_BLOCKS_PER_WORKER = 1

#: blocks of the matched filter's candidates scored per worker (their whole-scan
#: searches differ in cost: a few blocks each even the load)
SCORE_BLOCKS_PER_WORKER = 2


def shot_ranges(n_shots: int, n_parts: int) -> list[tuple[int, int]]:
    """Split 0..n_shots into ``n_parts`` contiguous ranges of nearly equal length."""
    edges = np.linspace(0, n_shots, max(1, int(n_parts)) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def block_work(blocks: Sequence[PeakBlock], n_steps: int, n_codes: int) -> list[float]:
    """The fusion's work of each block of peaks (its entries,
    :func:`~mems_stereo.pipeline.block_fusion.fusion_work`)."""
    return [float(fusion_work(b.counts, b.stop - b.start, n_steps, n_codes).sum())
            for b in blocks]


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
