"""The processing chain of one recording, streamed in chunks of shots.

:func:`process_recording` calls the stages in the paper's order: the scan angle of
every shot (:mod:`~mems_stereo.pipeline.angles`), the interval table compiled per
angle step (:mod:`~mems_stereo.pipeline.intervals`), pass 1 — classify and
histogram (:func:`~mems_stereo.pipeline.pass1.accumulate_range`) — the peak detector
(:func:`~mems_stereo.pipeline.peaks.find_peaks`) and the matched filter's
confirmation of its near misses (:func:`matched_stage`), pass 2 — the signal
detections inside each peak's window counted by (peak, scan-angle step, code)
(:func:`count_peaks`) — and the fusion of each peak's detections into one point
(:func:`~mems_stereo.pipeline.block_fusion.fuse_in_blocks`).

Every pass is a function of a shot range and returns arrays that add up
(histograms, counts, peak counts: all integers), so the Dask runner
(:mod:`mems_stereo.pipeline.distributed`), which calls the same stages on its
workers, and any chunk size give results identical to one process, bit for bit.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field, replace

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io.recording import Recording, RecordingHeader, read_header
from mems_stereo.model.system import System
from mems_stereo.pipeline.angles import shot_angles
from mems_stereo.pipeline.block_fusion import fuse_in_blocks
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.consistency import truth_suffix
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.matched import CandidateScores, confirm, merge_peaks
from mems_stereo.pipeline.pass1 import (
    COMPILE_SLOTS,
    Counts,
    RangeAccumulation,
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
from mems_stereo.pipeline.peak_support import pixel_log_range
from mems_stereo.pipeline.peak_table import Candidates, Peaks
from mems_stereo.pipeline.peaks import find_peaks
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange
from mems_stereo.pipeline.signal_store import (
    SignalStore,
    peak_counts_from_store,
    rereading_decompresses,
)
from mems_stereo.util.atomic import atomic_output
from mems_stereo.util.memory import HeapTrimmer
from mems_stereo.util.packing import pack_histograms, unpack_histograms
from mems_stereo.util.stopwatch import Stopwatch

#: pixel-slots of a recording from which a run trims the heap between its stages
#: (:class:`~mems_stereo.util.memory.HeapTrimmer`; small recordings: nothing to gain)
TRIM_SLOTS = 1 << 24


@dataclass
class ProcessResult:
    """Everything processing produced for one recording.

    Attributes
    ----------
    histograms : dict of (H, W, n_bins) int64 ``raw``, ``signal``, ``noise``
        (index N−1 holds code N).
    background_hz : (H, W) float64, ML background rate per pixel from the noise
        histogram (pile-up aware).
    peaks : :class:`~mems_stereo.pipeline.peak_table.Peaks`, (Q,) arrays ``row``, ``col``,
        ``code`` (peak code), ``code_lo``, ``code_hi`` (window), ``counts``, ….
    cloud : :class:`~mems_stereo.pipeline.cloud.PointCloud`, one point per peak.
    counts : :class:`~mems_stereo.pipeline.pass1.Counts` (shots,
        shots_unknown_angle, raw, signal, noise, peaks, points).
    truth : dict with recall and noise rejection (None without truth).
    theta : (K,) float64 rad, each shot's scan angle (NaN where unknown);
        valid : (K,) bool, where it is known.
    timings : seconds per stage.
    """

    system: System
    source: str
    histograms: dict[str, np.ndarray]
    background_hz: np.ndarray
    peaks: Peaks
    cloud: PointCloud
    counts: Counts
    truth: dict | None
    theta: np.ndarray
    valid: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    def __repr__(self) -> str:
        c = self.counts
        return (f"<ProcessResult {self.source}: {c['shots']} shots, {c['raw']} raw, "
                f"{c['signal']} signal, {c['peaks']} peaks, {c['points']} points"
                f"{truth_suffix(self.truth)}>")

    def __getstate__(self):
        # compact between processes (Dask): :func:`~mems_stereo.util.packing.pack_histograms`
        return {**self.__dict__, "histograms": pack_histograms(self.histograms)}

    def __setstate__(self, d):
        self.__dict__.update({**d, "histograms": unpack_histograms(d["histograms"])})


@dataclass(frozen=True, slots=True)
class RunInputs:
    """What the stages of a run read besides each other's results.

    source : the recording (a path, str, or a :class:`Recording`).
    system : the system processed with.  settings : the run's :class:`Settings`.
    table : the run's interval table (rows filled as the stages need them).
    theta : (K,) float64 rad, each shot's scan angle; valid : (K,) bool, where known.
    shape : (K, H, W), shots × receiver rows × columns.
    """

    source: str | Recording
    system: System
    settings: Settings
    table: IntervalTable
    theta: np.ndarray
    valid: np.ndarray
    shape: tuple[int, int, int]

    @property
    def shots(self) -> ShotRange:
        """Every shot of the recording, with its angle."""
        return ShotRange(self.theta, self.valid)


@dataclass(frozen=True, slots=True)
class Histograms:
    """The code histograms of a run, each (H, W, n_bins) int64 (index N−1: code N):
    ``raw`` every detection, ``signal`` the consistent ones, ``noise`` = raw − signal."""

    raw: np.ndarray
    signal: np.ndarray
    noise: np.ndarray

    @classmethod
    def of(cls, acc: RangeAccumulation, height: int, width: int) -> Histograms:
        """The histograms of pass 1's (P, n_bins + 1) counts (code 0, no detection,
        left out)."""
        n_bins = acc.hist_raw.shape[1] - 1
        raw = acc.hist_raw[:, 1:].astype(np.int64).reshape(height, width, n_bins)
        sig = acc.hist_signal[:, 1:].astype(np.int64).reshape(height, width, n_bins)
        return cls(raw, sig, raw - sig)


@dataclass(frozen=True, slots=True)
class CandidateCounts:
    """The matched filter's candidates and their pass-2 counts.

    candidates : :class:`~mems_stereo.pipeline.peak_table.Candidates` (the first
        stage's near misses and unpeaked pixels).
    counts : their :class:`~mems_stereo.pipeline.pass2.PeakCounts` (None where they
        stay on the Dask workers, which score the candidates there).
    joint : from a :class:`SignalStore`, the counts of the first stage's peaks and the
        candidates' widened windows in one pass, from which :func:`count_peaks` selects
        the confirmed peaks'; None when counted from the shots.
    """

    candidates: Candidates
    counts: PeakCounts | None
    joint: PeakCounts | None = None


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

    Examples
    --------
    >>> result = ms.process_recording(ms.data.path("room.h5"))
    >>> result.counts.peaks, result.counts.points
    (78, 73)
    >>> cloud = result.cloud
    >>> cloud.points.shape, cloud.points.dtype
    ((73, 3), dtype('float64'))
    >>> bool((cloud.attributes["range"] > 1.0).all())
    True
    """
    clock = Stopwatch()
    source = as_source(path)
    header = checked_header(source, system)
    sysm = header.system if system is None else system
    trim = HeapTrimmer(math.prod(header.shape) >= TRIM_SLOTS)
    theta, valid = trim.after(recording_angles(header, sysm))
    run = RunInputs(source, sysm, Settings() if settings is None else settings,
                    run_table(sysm, settings) if table is None else table, theta, valid,
                    header.shape)
    timings = {"read_header": clock.lap()}
    with SignalStore() as store:
        kept = store if keeps_signal(run) else None
        acc = pass1_stage(run, labels_path, progress, kept)
        counting = kept if kept is not None and kept.complete else None
        if table is None:
            run.table.save_cache()
        timings["classify_histogram"] = clock.lap()
        hists = trim.after(Histograms.of(acc, *header.shape[1:]))
        first, background = trim.after(find_peaks(
            sysm, hists.signal, hists.noise, theta, valid, run.settings,
            signal_angle=acc.hist_angle, table=run.table, n_per_step=acc.n_per_step))
        cc = count_candidates(run, first, counting)
        peaks = matched_stage(sysm, first, cc, run.table, acc.n_per_step, run.settings)
        timings["peaks"] = clock.lap()
        counts = trim.after(count_peaks(run, first, cc, peaks, counting, progress))
        timings["peak_detections"] = clock.lap()
        cloud = fuse_in_blocks(sysm, peaks, counts, run.settings, acc.n_per_step, run.table)
    peaks = replace(peaks, background_by_step=None)  # (Q, S): used up; keep results light
    timings["points"] = clock.lap()
    if table is None:  # the fusion fills rows of its peaks' bands: keep them for the next run
        run.table.save_cache()
    return result_of(run, acc, hists, background, peaks, cloud, timings)


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
        raise FormatError(f"expected a recording path, a Recording or chunks of shots "
                          f"(Recordings), found {type(recording).__name__}",
                          field="recording")
    return Recording.concatenate(chunks)


def checked_header(source, system: System | None) -> RecordingHeader:
    """The recording's header (validated on read), its shots' shape checked against the
    receiver of the system processed with (``system``, default the recording's)."""
    header = read_header(source)
    sysm = header.system if system is None else system
    if header.shape[1:] != (sysm.receiver.height, sysm.receiver.width):
        raise FormatError(f"expected shape (K, {sysm.receiver.height}, {sysm.receiver.width}) "
                          f"of the processing system, found {header.shape}", str(source),
                          "/shots/bins")
    return header


def recording_angles(header: RecordingHeader, system: System):
    """``(theta, valid)`` of every shot (:func:`shot_angles`); the header's shot times,
    O(K) memory that no later stage reads, are dropped."""
    angles = shot_angles(header, system)
    header.shot_time = None
    return angles


def run_table(system: System, settings: Settings | None) -> IntervalTable:
    """The run's interval table with the rows of its disk cache."""
    table = IntervalTable.for_settings(system, Settings() if settings is None else settings)
    table.load_cache()
    return table


def keeps_signal(run: RunInputs) -> bool:
    """Whether pass 1 keeps its signal detections for pass 2 (a
    :class:`SignalStore`): compiled-size recordings whose shots are compressed (small
    recordings and uncompressed files: reading them again costs less)."""
    return math.prod(run.shape) >= COMPILE_SLOTS and rereading_decompresses(run.source)


@contextlib.contextmanager
def _labels_file(path, n_shots: int, shape):
    """Context: an HDF5 labels file written atomically; yields ``(file, /label dataset)``."""
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = "mems-stereo/labels"
        f.attrs["version"] = 1
        ds = f.create_dataset("label", shape=(n_shots,) + tuple(shape), dtype=np.uint8,
                              chunks=(max(1, min(n_shots, 4096)),) + tuple(shape),
                              compression="gzip")
        yield f, ds


def pass1_stage(run: RunInputs, labels_path, progress,
                store: SignalStore | None) -> RangeAccumulation:
    """Pass 1 over the whole recording (:func:`accumulate_range`): the labels written to
    ``labels_path`` (with each shot's angle) where given, the signal detections kept in
    ``store`` where given."""
    if labels_path is None:
        return accumulate_range(run.source, run.system, run.shots, run.settings,
                                progress=progress, table=run.table, signal_store=store)
    with _labels_file(labels_path, run.shape[0], run.shape[1:]) as (f, ds):
        acc = accumulate_range(run.source, run.system, run.shots, run.settings,
                               labels_out=ds, progress=progress, table=run.table,
                               signal_store=store)
        f.create_dataset("theta", data=np.where(run.valid, run.theta, np.nan))
    return acc


def candidates_of(first: Peaks) -> Candidates | None:
    """The matched filter's candidates of the first stage's peaks; None where none."""
    cands = first.candidates
    return cands if cands is not None and len(cands) else None


def count_candidates(run: RunInputs, first: Peaks,
                     store: SignalStore | None) -> CandidateCounts | None:
    """Pass 2 of the matched filter's candidates (None: no candidates): from the shots,
    or from ``store``, where one pass counts the first stage's peaks with the
    candidates' windows widened to hold any peak they confirm (each set's counts are
    then filtered from it: the same integers as counting it alone)."""
    cands = candidates_of(first)
    if cands is None:
        return None
    if store is None:
        return CandidateCounts(cands, peak_counts_range(
            run.source, run.system, run.shots, run.settings, cands, table=run.table))
    S, nb = run.table.n_steps, run.system.tdc.n_bins + 1
    joint = peak_counts_from_store(store, run.system, with_widened_candidates(first, cands, S),
                                   S)
    return CandidateCounts(cands, select_counts(joint, candidate_selection(len(first), cands),
                                                S, nb), joint)


def matched_stage(system: System, first: Peaks, cc: CandidateCounts | None,
                  table: IntervalTable, n_per_step, settings: Settings,
                  scores: CandidateScores | None = None) -> Peaks:
    """The first stage's peaks plus the near misses that the matched filter over
    angle × code confirms (:mod:`mems_stereo.pipeline.matched`), merged in pixel order.

    ``cc`` : the candidates and their counts (:func:`count_candidates`; None: no
    candidates); ``scores`` : the candidates' scores where computed elsewhere (the Dask
    runner's blocks; ``cc.counts`` is then not read)."""
    if cc is None:
        return first
    new = confirm(system, cc.candidates, cc.counts, table, n_per_step, settings, first,
                  log_range_of=lambda pix, j: pixel_log_range(system, table, pix, j),
                  scores=scores)
    return merge_peaks(first, new)


def count_peaks(run: RunInputs, first: Peaks, cc: CandidateCounts | None, peaks: Peaks,
                store: SignalStore | None, progress=None) -> PeakCounts:
    """Pass 2 of ``peaks``: from the shots, or from ``store`` (the confirmed peaks'
    counts selected from the candidates' joint count where there is one)."""
    if store is None:
        return peak_counts_range(run.source, run.system, run.shots, run.settings, peaks,
                                 progress=progress, table=run.table)
    S, nb = run.table.n_steps, run.system.tdc.n_bins + 1
    if cc is not None and cc.joint is not None:
        pc = select_counts(cc.joint, merged_selection(first, cc.candidates, peaks,
                                                      run.system.receiver.width), S, nb)
    else:
        pc = peak_counts_from_store(store, run.system, peaks, S)
    if progress is not None:
        progress(run.shape[0])
    return pc


def result_of(run: RunInputs, acc: RangeAccumulation, hists: Histograms, background,
              peaks: Peaks, cloud: PointCloud, timings: dict[str, float]) -> ProcessResult:
    """The :class:`ProcessResult` of a run's stages (the shots' unknown angles NaN)."""
    counts = Counts(int(run.shape[0]), int(acc.n_unknown), int(hists.raw.sum()),
                    int(hists.signal.sum()), int(hists.noise.sum()), len(peaks),
                    len(cloud))
    truth = truth_scores(acc.confusion) if acc.has_truth else None
    run.theta[~run.valid] = np.nan  # (already NaN where the angle is unknown; no copy)
    source = run.source.source if isinstance(run.source, Recording) else str(run.source)
    return ProcessResult(run.system, source, {"raw": hists.raw, "signal": hists.signal,
                                              "noise": hists.noise},
                         background, peaks, cloud, counts, truth, run.theta, run.valid,
                         timings)
