"""The processing chain of one recording, streamed in chunks of shots.

Two passes over ``/shots/bins``, each in chunks (memory does not grow with
the recording's length):

1. **classify and accumulate** (:func:`accumulate_range`): scan angle per
   shot from the zero crossings, labels from the compiled interval table
   (:mod:`mems_stereo.pipeline.intervals`, identical to the NumPy reference on the
   snapped angles), raw and signal histograms per pixel; optionally the
   labels file and, where the recording has ``/truth/label``, the confusion
   counts against the truth.
2. **peaks → points** (:func:`peak_counts_range`): after the peak detector
   has found each pixel's peak code window in the signal histogram, the
   signal detections inside the windows are counted by (peak, scan-angle
   step, code) — exact integers (:class:`PeakCounts`) — and each distinct
   triple is triangulated once, weighted by its count, and fused into one
   point per peak (:func:`points_from_counts`).

Every step is a function of a shot range and returns arrays that add up
(histograms, counts, peak counts: all integers), so the Dask runner
(:mod:`mems_stereo.pipeline.distributed`) and any chunk size give results identical
to one process, bit for bit.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import h5py
import numpy as np

from mems_stereo.errors import ShapeError
from mems_stereo.io.recording import Recording, read_header
from mems_stereo.model.system import System
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.consistency import truth_suffix
from mems_stereo.pipeline.first_photon_correction import FP_BLOCK
from mems_stereo.pipeline.fusion import (
    accumulator_for_peaks,
    consistent_points,
    peak_sums_from_counts,
    points_from_counts,
)
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.pass1 import (
    COMPILE_SLOTS,
    Counts,
    RangeAccumulation,
    _pack,
    _unpack,
    accumulate_range,
    truth_scores,
)
from mems_stereo.pipeline.pass2 import (
    PeakCounts,
    candidate_selection,
    merged_selection,
    peak_counts_range,
    select_counts,
    with_widened_candidates,
)
from mems_stereo.pipeline.peak_means import PeakMeans
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.signal_store import (
    SignalStore,
    peak_counts_from_store,
    rereading_decompresses,
)
from mems_stereo.util.atomic import atomic_output


@dataclass
class ProcessResult:
    """Everything processing produced for one recording.

    histograms : dict of (H, W, n_bins) int64 ``raw``, ``signal``, ``noise``
        (index N−1 holds code N).
    background_hz : (H, W) float64, ML background rate per pixel from the noise
        histogram (pile-up aware).
    peaks : dict of (Q,) arrays ``row``, ``col``, ``code`` (peak code),
        ``code_lo``, ``code_hi`` (window), ``counts``.
    cloud : :class:`~mems_stereo.pipeline.cloud.PointCloud`, one point per peak.
    counts : :class:`~mems_stereo.pipeline.pass1.Counts` (shots,
        shots_unknown_angle, raw, signal, noise, peaks, points; also a mapping).
    truth : dict with recall and noise rejection (None without truth).
    timings : dict of seconds per stage.
    """

    system: System
    source: str
    histograms: dict
    background_hz: np.ndarray
    peaks: dict
    cloud: PointCloud
    counts: dict
    truth: dict | None
    theta: np.ndarray
    valid: np.ndarray
    timings: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        c = self.counts
        return (f"<ProcessResult {self.source}: {c['shots']} shots, {c['raw']} raw, "
                f"{c['signal']} signal, {c['peaks']} peaks, {c['points']} points"
                f"{truth_suffix(self.truth)}>")

    def __getstate__(self):
        # compact between processes (Dask): raw and signal as uint32 where every
        # count fits (non-zero entries only when smaller); noise = raw − signal
        d = dict(self.__dict__)
        h = dict(d["histograms"])
        if set(h) == {"raw", "signal", "noise"}:
            for k in ("raw", "signal"):
                a = h[k]
                if a.dtype == np.int64 and a.size and 0 <= a.min() and a.max() < 2 ** 32:
                    a = a.astype(np.uint32)
                h[k] = _pack(a)
            del h["noise"]
            h["_packed"] = True
        d["histograms"] = h
        return d

    def __setstate__(self, d):
        h = d["histograms"]
        if h.pop("_packed", False):
            raw = _unpack(h["raw"]).astype(np.int64)
            sig = _unpack(h["signal"]).astype(np.int64)
            h = {"raw": raw, "signal": sig, "noise": raw - sig}
        d["histograms"] = h
        self.__dict__.update(d)


def _labels_file(path, K: int, shape):
    """Context: an HDF5 labels file written atomically; yields the /label dataset."""
    import contextlib

    @contextlib.contextmanager
    def ctx():
        with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["format"] = "mems-stereo/labels"
            f.attrs["version"] = 1
            ds = f.create_dataset("label", shape=(K,) + tuple(shape), dtype=np.uint8,
                                  chunks=(max(1, min(K, 4096)),) + tuple(shape),
                                  compression="gzip")
            yield f, ds

    return ctx()


def as_source(recording) -> str | Recording:
    """What the passes read shots from: a path (str) or a :class:`Recording`.

    ``recording`` : a path (str or os.PathLike) of a FORMAT v1 file, a
    :class:`Recording`, or an iterable of Recordings that are consecutive
    chunks of shots of one acquisition (joined with :meth:`Recording.concatenate`).
    """
    if isinstance(recording, Recording):
        return recording
    if isinstance(recording, (str, os.PathLike)):
        return os.fspath(recording)
    if isinstance(recording, bytes):
        return os.fsdecode(recording)
    try:
        chunks = list(recording)
    except TypeError:
        chunks = None
    if not chunks or not all(isinstance(c, Recording) for c in chunks):
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected a recording path, a Recording or chunks of shots "
                          f"(Recordings), found {type(recording).__name__}",
                          field="recording")
    return Recording.concatenate(chunks)


def process_recording(path, system: System | None = None,
                      settings: Settings | None = None, labels_path=None,
                      progress=None, table: IntervalTable | None = None) -> ProcessResult:
    """Classify, histogram, find peaks and triangulate one recording (streamed).

    Parameters
    ----------
    path : a FORMAT v1 recording file (validated on read; see docs/formats.md),
        a :class:`~mems_stereo.io.recording.Recording` in memory
        (``ms.read_recording(...)``), or an iterable of Recordings that are
        consecutive chunks of shots of one acquisition.
    system : system to process with (default: the recording's ``/system``),
        e.g. a calibrated one.
    settings : :class:`Settings`.
    labels_path : write the event labels (FORMAT v1 outputs) there.
    progress : callable(n_shots_done) for progress bars.
    table : the :class:`~mems_stereo.pipeline.intervals.IntervalTable` of
        ``system`` and ``settings`` (e.g. filled once and shared by the Dask
        runner); default: built here, once, with the rows of its disk cache,
        and passed to every stage (rows filled here go back to the cache).
    """
    st = Settings() if settings is None else settings
    t0 = time.perf_counter()
    path = as_source(path)
    header = read_header(path)
    sysm = header.system if system is None else system
    K, H, W = header.shape
    if (H, W) != (sysm.receiver.height, sysm.receiver.width):
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected shape (K, {sysm.receiver.height}, {sysm.receiver.width}) "
                          f"of the processing system, found {header.shape}", str(path),
                          "/shots/bins")
    theta, valid = shot_angles(header, sysm)
    header.shot_time = None  # only the angles are needed from here on: free O(K) memory
    if K * H * W >= TRIM_SLOTS:  # the angles' O(K) temporaries
        release_freed_memory()
    own_table = table is None
    if own_table:
        table = IntervalTable.for_settings(sysm, st)
        table.load_cache()
    timings = {"read_header": time.perf_counter() - t0}

    # compiled ranges of compressed files keep pass 1's signal detections, so that
    # pass 2 needs no second decompression of the shots (small recordings and
    # uncompressed files: reading them again costs less)
    with SignalStore() as store:
        keep = (store if K * H * W >= COMPILE_SLOTS and rereading_decompresses(path)
                else None)
        t1 = time.perf_counter()
        if labels_path is not None:
            with _labels_file(labels_path, K, (H, W)) as (f, ds):
                acc = accumulate_range(path, sysm, theta, valid, st, labels_out=ds,
                                       progress=progress, table=table, signal_store=keep)
                f.create_dataset("theta", data=np.where(valid, theta, np.nan))
        else:
            acc = accumulate_range(path, sysm, theta, valid, st, progress=progress, table=table,
                                   signal_store=keep)
        if own_table:
            table.save_cache()
        timings["classify_histogram"] = time.perf_counter() - t1
        count_peaks = count_candidates = detect = None
        if keep is not None and store.complete:
            S, nb = table.n_steps, sysm.tdc.n_bins + 1
            seen = {}

            def detect(sig, noise):  # find_peaks, keeping the first stage's peaks
                from mems_stereo.pipeline.peaks import find_peaks

                seen["first"], bg = find_peaks(sysm, sig, noise, theta, valid, st,
                                               signal_angle=acc.hist_angle, table=table,
                                               n_per_step=acc.n_per_step)
                return seen["first"], bg

            def count_candidates(cands):
                # one pass over the store for the candidates (over windows widened to
                # hold any peak they confirm) and the first stage's peaks; each set's
                # counts are filtered from it (the same integers as counting it alone)
                seen["cands"] = cands
                seen["both"] = peak_counts_from_store(
                    store, sysm, with_widened_candidates(seen["first"], cands, S), S)
                return select_counts(seen["both"],
                                     *candidate_selection(len(seen["first"]), cands), S, nb)

            def count_peaks(peaks):
                if "both" in seen:
                    pc = select_counts(seen.pop("both"), *merged_selection(
                        seen["first"], seen["cands"], peaks, sysm.receiver.width), S, nb)
                else:
                    pc = peak_counts_from_store(store, sysm, peaks, S)
                if progress is not None:
                    progress(K)
                return pc
        res = finish_processing(path, sysm, header, theta, valid, acc, st, timings,
                                count_peaks=count_peaks, progress=progress, table=table,
                                count_candidates=count_candidates, detect=detect)
    if own_table:  # the fusion fills rows of its peaks' bands: keep them for the next run
        table.save_cache()
    return res


def finish_processing(path, sysm, header, theta, valid, acc: RangeAccumulation, st: Settings,
                      timings: dict, count_peaks=None, progress=None,
                      table: IntervalTable | None = None, make_points=None,
                      count_candidates=None, detect=None,
                      score_candidates=None) -> ProcessResult:
    """Peaks, background and points from the accumulated histograms.

    ``count_peaks(peaks) -> PeakCounts`` runs pass 2 over the whole recording
    (default: here, in chunks; the Dask runner passes its own, which may
    return a handle that only its ``make_points`` reads).
    ``make_points(peaks, counts) -> PointCloud`` runs the fusion (default:
    :func:`points_from_counts` here; the Dask runner fuses blocks of peaks on
    its workers).  ``table`` : the run's interval table (the one pass 1 filled).
    ``count_candidates(peaks) -> PeakCounts`` counts the matched filter's
    candidates (default: a pass over the recording's shots; a run with a
    :class:`SignalStore` counts from the store, the same integers).
    ``detect(signal, noise) -> (Peaks, background_hz)`` runs the peak detector
    (default: :func:`~mems_stereo.pipeline.peaks.find_peaks` here, on
    ``acc.hist_angle``; the Dask runner scores blocks of pixels on its workers).
    ``score_candidates(candidates, counts) -> dict`` the matched filter's
    per-candidate search (default: :func:`~mems_stereo.pipeline.matched.score_candidates`
    here; the Dask runner scores blocks of candidates where their counts are).
    """
    from mems_stereo.pipeline.peaks import find_peaks

    K, H, W = header.shape
    n_bins = sysm.tdc.n_bins
    if table is None:
        table = IntervalTable.for_settings(sysm, st)
    t2 = time.perf_counter()
    raw = acc.hist_raw[:, 1:].astype(np.int64).reshape(H, W, n_bins)
    sig = acc.hist_signal[:, 1:].astype(np.int64).reshape(H, W, n_bins)
    noise = raw - sig
    big = K * H * W >= TRIM_SLOTS
    if big:  # pass 1's freed chunks, before the detector's (P, S) temporaries
        release_freed_memory()
    if detect is None:
        peaks, background = find_peaks(sysm, sig, noise, theta, valid, st,
                                       signal_angle=acc.hist_angle, table=table,
                                       n_per_step=acc.n_per_step)
    else:
        peaks, background = detect(sig, noise)
    if big:  # the detector's (P, S) temporaries are freed: give them back
        release_freed_memory()
    peaks = matched_stage(path, sysm, theta, valid, st, peaks, table, acc.n_per_step,
                          count_candidates, score_candidates)
    timings["peaks"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if count_peaks is None:
        counts = peak_counts_range(path, sysm, theta, valid, st, peaks, progress=progress,
                                   table=table)
    else:
        counts = count_peaks(peaks)
    if big:  # pass 2's merge temporaries, before the fusion's
        release_freed_memory()
    timings["peak_detections"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    if make_points is None:
        cloud = fuse_in_blocks(sysm, peaks, counts, st, acc.n_per_step, table)
    else:
        cloud = make_points(peaks, counts)
    peaks.pop("background_by_step", None)  # (Q, S): used up; keep results light
    timings["points"] = time.perf_counter() - t4
    counts = Counts(int(K), int(acc.n_unknown), int(raw.sum()), int(sig.sum()),
                    int(noise.sum()), int(len(peaks["row"])), len(cloud))
    truth = truth_scores(acc.confusion) if acc.has_truth else None
    theta[~valid] = np.nan  # (already NaN where the angle is unknown; no copy)
    source = path.source if isinstance(path, Recording) else str(path)
    return ProcessResult(sysm, source, {"raw": raw, "signal": sig, "noise": noise},
                         background, peaks, cloud, counts, truth, theta, valid, timings)


def matched_stage(path, sysm, theta, valid, st: Settings, peaks, table, n_per_step,
                  count_candidates=None, score_candidates=None):
    """The first stage's peaks plus the near misses that the matched filter over
    angle × code confirms (:mod:`mems_stereo.pipeline.matched`; their detections
    are counted here, in one pass over the candidates' steps, or by
    ``count_candidates(candidates) -> PeakCounts``)."""
    from mems_stereo.pipeline.matched import confirm, merge_peaks
    from mems_stereo.pipeline.peaks import pixel_log_range

    cands = getattr(peaks, "candidates", None)
    if cands is None or len(cands) == 0:
        return peaks
    cc = (peak_counts_range(path, sysm, theta, valid, st, cands, table=table)
          if count_candidates is None else count_candidates(cands))
    W = sysm.receiver.width
    scores = None if score_candidates is None else score_candidates(cands, cc)
    new = confirm(sysm, cands, cc, table, n_per_step, st, cands.width, cands.n_windows,
                  peaks.pixel(W), (peaks.step_lo + peaks.step_hi) // 2,
                  log_range_of=lambda pix, j: pixel_log_range(sysm, table, pix, j),
                  scores=scores)
    return merge_peaks(peaks, new)


# --------------------------------------------------------------------------
# memory: freed heap back to the OS between stages

#: pixel-slots of a recording from which :func:`finish_processing` trims the heap
#: between its stages (small recordings: nothing to gain)
TRIM_SLOTS = 1 << 24
_TRIM: list = []


def release_freed_memory() -> bool:
    """Return the heap memory freed by the last stage to the OS (glibc's
    ``malloc_trim(0)``; a no-op where there is none); returns whether it ran.

    NumPy's temporaries below glibc's (growing) mmap threshold come from the
    heap, and freed heap pages stay resident: without this the peak RSS of
    a run adds each stage's temporaries to the freed ones of the stage
    before.  One call costs milliseconds (unlike ``MALLOC_TRIM_THRESHOLD_``,
    which trims at every free)."""
    if not _TRIM:
        try:
            import ctypes

            _TRIM.append(ctypes.CDLL("libc.so.6").malloc_trim)
        except (OSError, AttributeError):
            _TRIM.append(None)
    if _TRIM[0] is None:
        return False
    _TRIM[0](0)
    return True


# --------------------------------------------------------------------------
# the fusion in blocks of peaks: bounded memory here, one task each on Dask

#: most (peak, step, code) entries fused at once by :func:`fuse_in_blocks` (the
#: fusion's temporaries: about 85 MB at 2**16 entries, 110 MB at 2**18, 210 MB for the
#: 10**6 entries of a 2,000,000-shot floodlight recording in one block; the same CPU)
FUSE_ENTRIES = 1 << 16


def fuse_in_blocks(system, peaks, counts: PeakCounts, settings: Settings, n_per_step,
                   table: IntervalTable, max_entries: int | None = None):
    """:func:`points_from_counts` over blocks of peaks of at most about ``max_entries``
    distinct (peak, step, code) entries each (:func:`fused_sums`): the cloud of the
    joined accumulator is the whole's bit for bit, with the fusion's per-entry
    arrays (≈ 200 bytes an entry) bounded by the block instead of growing with the
    recording's distinct entries (default :data:`FUSE_ENTRIES`)."""
    cap = FUSE_ENTRIES if max_entries is None else max_entries
    if counts.keys.size <= cap:
        return points_from_counts(system, peaks, counts, settings, shots_per_step=n_per_step,
                                  table=table)
    acc = fused_sums(system, peaks, counts, settings, n_per_step, table, cap)
    return consistent_points(acc.cloud(settings.min_counts), settings.confidence)


def fused_sums(system, peaks, counts: PeakCounts, settings: Settings, n_per_step,
               table: IntervalTable, max_entries: int | None = None):
    """The :class:`~mems_stereo.pipeline.fusion.PeakAccumulator` of ``peaks`` (a mapping
    of (Q,) arrays) after both sub-passes over ``counts``, computed over blocks of
    peaks of at most about ``max_entries`` distinct entries each (default
    :data:`FUSE_ENTRIES`; cut at multiples of ``FP_BLOCK`` peaks) and joined
    (:meth:`~mems_stereo.pipeline.fusion.PeakAccumulator.joined`): a peak's sums are its
    entries' alone, so the result is the one accumulator of every entry, bit for bit.
    The fusion's cost per entry grows with the block (its temporaries), so the Dask
    runner's blocks of peaks are cut the same way on their workers."""
    cap = FUSE_ENTRIES if max_entries is None else max_entries
    light = {k: v for k, v in peaks.items() if k != "background_by_step" and v is not None}
    n_blocks = max(1, math.ceil(counts.keys.size / max(1, int(cap))))
    if n_blocks == 1:
        return peak_sums_from_counts(system, light, counts, settings, n_per_step, table)
    # each block's sums (a peak's are its entries' alone), joined: no halo of
    # neighbours to fuse twice (the cloud's depth edges are made on the joined sums)
    blocks = split_peak_counts(counts, len(light["row"]), table.n_steps,
                               system.tdc.n_bins + 1, n_blocks)
    parts = [peak_sums_from_counts(system, {k: np.asarray(v)[q0:q1] for k, v in light.items()},
                                   c, settings, n_per_step, table) for q0, q1, c in blocks]
    return accumulator_for_peaks(system, light, settings, n_per_step, table).joined(parts)


def block_with_halo(system, peaks, blocks, i: int, n_steps: int):
    """Peaks to fuse for block ``i``: its own and a halo, ``(sel (Q',) int64 sorted,
    counts of sel renumbered 0..Q'−1, own (a, b) local range of the block's peaks)``.

    The fusion of a peak depends on its row neighbours (column ± 1: the depth
    edges of :meth:`PeakAccumulator.cloud`), so the halo holds every peak of a
    pixel beside one of the block's; it is widened to whole groups of
    ``FP_BLOCK`` peaks by index, so the first-photon step groups every peak as
    the whole run does and the halo's points are the whole's, bit for bit.
    """
    q0, q1, _ = blocks[i]
    rows = np.asarray(peaks["row"], np.int64)
    cols = np.asarray(peaks["col"], np.int64)
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
    for b0, b1, c in blocks:
        if b1 <= b0 or c.keys.size == 0 or not np.any((sel >= b0) & (sel < b1)):
            continue
        gq = c.keys // span + b0
        m = np.isin(gq, sel)
        keys.append(np.searchsorted(sel, gq[m]) * span + c.keys[m] % span)
        vals.append(c.counts[m])
    counts = (PeakCounts(np.concatenate(keys), np.concatenate(vals)) if keys
              else PeakCounts())
    own = (int(np.searchsorted(sel, q0)), int(np.searchsorted(sel, q1)))
    return sel, counts, own


def points_block(system, peaks, blocks, i: int, settings: Settings, n_per_step, table):
    """The cloud of the peaks of block ``i`` of ``blocks`` (:func:`split_peak_counts`;
    ``peaks`` a mapping of (Q,) arrays), fused with the halo of
    :func:`block_with_halo`: the blocks' clouds joined are the whole's, bit for bit."""
    sel, counts, own = block_with_halo(system, peaks, blocks, i, table.n_steps)
    sub = {k: np.asarray(v)[sel] for k, v in peaks.items() if v is not None}
    return points_from_counts(system, sub, counts, settings, shots_per_step=n_per_step,
                              table=table, own=own)


def means_block(system, peaks, blocks, i: int, settings: Settings, n_per_step, table):
    """The :class:`~mems_stereo.pipeline.peak_means.PeakMeans` of the peaks of block ``i``
    of ``blocks`` (:func:`split_peak_counts`; ``peaks`` a mapping of (Q,) arrays),
    no halo: the blocks' means joined (``PeakMeans.concat``) give the whole's cloud,
    bit for bit (:func:`cloud_of_means`).  A block of more than :data:`FUSE_ENTRIES`
    entries is fused in sub-blocks (:func:`fused_sums`), as one process does."""
    q0, q1, counts = blocks[i]
    sub = {k: np.asarray(v)[q0:q1] for k, v in peaks.items() if v is not None}
    return fused_sums(system, sub, counts, settings, n_per_step, table).peak_means()


def cloud_of_means(means, settings: Settings):
    """The cloud of the joined means of consecutive peak blocks (consistent points)."""
    return consistent_points(PeakMeans.concat(means).cloud(settings.min_counts),
                             settings.confidence)


def peak_blocks(entries_per_peak, n_blocks: int, unit: int = FP_BLOCK) -> list[tuple[int, int]]:
    """Split the peaks 0..Q into at most ``n_blocks`` contiguous ranges ``(q0, q1)``.

    Cuts only at multiples of ``unit`` (the fusion's first-photon block
    :data:`~mems_stereo.pipeline.first_photon_correction.FP_BLOCK`, so the blocks' clouds joined are
    the whole's, bit for bit), each near an equal share of the fusion's work
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
                      n_blocks: int) -> list[tuple[int, int, PeakCounts]]:
    """``(q0, q1, counts of peaks q0..q1−1 renumbered from 0)`` per block of
    :func:`peak_blocks` (balanced by :func:`fusion_work`); keys are sorted by peak, so
    each block is a slice."""
    span = np.int64(n_steps) * np.int64(n_codes)
    keys = counts.keys
    out = []
    for q0, q1 in peak_blocks(fusion_work(counts, n_peaks, n_steps, n_codes), n_blocks):
        a, b = np.searchsorted(keys, [q0 * span, q1 * span])
        out.append((q0, q1, PeakCounts(keys[a:b] - q0 * span, counts.counts[a:b].copy())))
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
