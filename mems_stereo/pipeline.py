"""The processing chain of one recording, streamed in chunks of shots.

Two passes over ``/shots/bins``, each in chunks (memory does not grow with
the recording's length):

1. **classify and accumulate** (:func:`accumulate_range`): scan angle per
   shot from the zero crossings, labels from the compiled interval table
   (:mod:`mems_stereo.fastpath`, identical to the NumPy reference on the
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
(:mod:`mems_stereo.distributed`) and any chunk size give results identical
to one process, bit for bit.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from .classify import DEFAULT_CONFIDENCE
from .cloud import PointCloud
from .fastpath import classify_and_accumulate, interval_table, peak_window_keys, shots_per_step
from .io_util import atomic_output
from .recording import iter_shot_chunks, read_header
from .scanner import scan_angles
from .system import System

DEFAULT_CHUNK_SHOTS = 8192


@dataclass(frozen=True)
class Settings:
    """Processing settings (all documented in docs/pipeline.md).

    confidence : two-sided coverage of the consistency bound (0.997 = 3σ).
    min_range : optional prior, m: no target nearer than this (None: none).
    chunk_shots : shots per chunk read from the file.
    smoothing_bins : width of the moving-average filter of the histograms
        (default: the laser pulse's FWHM in bins, at least 1).
    false_alarm : per-pixel probability that background alone crosses the
        peak threshold.
    min_counts : fewest signal counts for a peak.
    """

    confidence: float = DEFAULT_CONFIDENCE
    min_range: float | None = None
    chunk_shots: int = DEFAULT_CHUNK_SHOTS
    smoothing_bins: int | None = None
    false_alarm: float = 1e-3
    min_counts: int = 3


@dataclass
class RangeAccumulation:
    """What pass 1 returns for a shot range; sums over ranges with ``+``.

    hist_raw, hist_signal : (P, n_bins + 1) int64, column N = code N (column
        0: valid pixel-slots without detection).
    hist_angle : (P, S) int64, signal detections per pixel and scan-angle step
        of the interval table.
    n_shots, n_unknown : shots in the range and those of unknown angle.
    confusion : (3, 3) int64, truth label (row) × assigned label (column),
        zeros when there is no truth.
    has_truth : bool.
    """

    hist_raw: np.ndarray
    hist_signal: np.ndarray
    hist_angle: np.ndarray
    n_shots: int
    n_unknown: int
    confusion: np.ndarray
    has_truth: bool

    def __add__(self, other: RangeAccumulation) -> RangeAccumulation:
        return RangeAccumulation(self.hist_raw + other.hist_raw,
                                 self.hist_signal + other.hist_signal,
                                 self.hist_angle + other.hist_angle,
                                 self.n_shots + other.n_shots, self.n_unknown + other.n_unknown,
                                 self.confusion + other.confusion,
                                 self.has_truth and other.has_truth)


def shot_angles(header, system: System, block: int = 1 << 20):
    """(theta, valid) of every shot of a recording header, from its zero crossings.

    Computed in blocks of shots so the temporaries stay small for long recordings.
    """
    t = header.shot_time
    theta = np.empty(t.shape, np.float64)
    valid = np.empty(t.shape, bool)
    for a in range(0, t.size, block):
        theta[a:a + block], valid[a:a + block] = scan_angles(
            t[a:a + block], header.zero_crossings, header.rising, system.scanner)
    return theta, valid


def accumulate_range(path, system: System, theta, valid, settings: Settings,
                     start: int = 0, stop: int | None = None, labels_out=None,
                     progress=None) -> RangeAccumulation:
    """Pass 1 over shots [start, stop): labels and histograms.

    ``theta``, ``valid`` : (K,) for the WHOLE recording (indexed by shot).
    ``labels_out`` : an h5py dataset (K, H, W) uint8 to write labels into, or None.
    """
    P = system.receiver.width * system.receiver.height
    n_bins = system.tdc.n_bins
    table = interval_table(system, settings.confidence, min_range=settings.min_range)
    raw = np.zeros((P, n_bins + 1), np.int64)
    sig = np.zeros((P, n_bins + 1), np.int64)
    raw32 = np.zeros((P, n_bins + 1), np.int32)
    sig32 = np.zeros((P, n_bins + 1), np.int32)
    angle = np.zeros((P, table.n_steps), np.int64)
    conf = np.zeros((3, 3), np.int64)
    has_truth = True
    n_shots = n_unknown = 0
    for s0, _t, bins, truth in iter_shot_chunks(path, settings.chunk_shots, start, stop,
                                                truth_labels=True):
        s1 = s0 + bins.shape[0]
        th, v = theta[s0:s1], valid[s0:s1]
        raw32[:] = 0
        sig32[:] = 0
        want = labels_out is not None or truth is not None
        labels, _, _ = classify_and_accumulate(bins, th, v, table, n_bins, raw32, sig32,
                                               want_labels=want, hist_angle=angle)
        raw += raw32
        sig += sig32
        if labels_out is not None:
            labels_out[s0:s1] = labels
        if truth is None:
            has_truth = False
        else:
            tl = np.asarray(truth, dtype=np.int64)
            conf += np.bincount((tl * 3 + labels).ravel(), minlength=9).reshape(3, 3)
        n_shots += s1 - s0
        n_unknown += int(np.count_nonzero(~v))
        if progress is not None:
            progress(s1 - s0)
    return RangeAccumulation(raw, sig, angle, n_shots, n_unknown, conf, has_truth)


class PeakCounts:
    """How often each distinct (peak, scan-angle step, code) occurs among the signal
    detections inside the peak windows: integers, so sums over chunks and workers
    are exact in any order.

    Keys are ``(peak · S + step) · (n_bins + 1) + code`` with S the interval
    table's number of angle steps; ``keys`` (U,) int64 sorted unique,
    ``counts`` (U,) int64.  New keys are buffered and merged when the buffer
    outgrows the merged set (amortised O(U log U)); memory is bounded by the
    number of distinct keys, not by the recording's length.
    """

    def __init__(self, keys=None, counts=None):
        self.keys = np.zeros(0, np.int64) if keys is None else np.asarray(keys, np.int64)
        self.counts = np.zeros(0, np.int64) if counts is None else np.asarray(counts, np.int64)
        self._pending: list[np.ndarray] = []
        self._n_pending = 0

    def add_keys(self, keys) -> None:
        k = np.asarray(keys, dtype=np.int64).ravel()
        if k.size:
            self._pending.append(k)
            self._n_pending += k.size
            if self._n_pending > max(1 << 20, self.keys.size):
                self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        new = np.concatenate(self._pending)
        self._pending, self._n_pending = [], 0
        k, c = np.unique(new, return_counts=True)
        allk = np.concatenate([self.keys, k])
        allc = np.concatenate([self.counts, c])
        u, inv = np.unique(allk, return_inverse=True)
        self.keys, self.counts = u, np.bincount(inv, weights=allc).astype(np.int64)

    def __add__(self, other: PeakCounts) -> PeakCounts:
        self._merge()
        other._merge()
        k = np.concatenate([self.keys, other.keys])
        c = np.concatenate([self.counts, other.counts])
        u, inv = np.unique(k, return_inverse=True)
        return PeakCounts(u, np.bincount(inv, weights=c).astype(np.int64))

    def finished(self) -> PeakCounts:
        self._merge()
        return self


def peak_counts_range(path, system: System, theta, valid, settings: Settings, peaks: dict,
                      start: int = 0, stop: int | None = None, progress=None) -> PeakCounts:
    """Pass 2 over shots [start, stop): count the peak windows' signal detections by
    (peak, angle step, code) — see :class:`PeakCounts` and
    :func:`mems_stereo.fastpath.peak_window_keys`."""
    table = interval_table(system, settings.confidence, min_range=settings.min_range)
    W = system.receiver.width
    pix = peaks["row"] * W + peaks["col"]
    pc = PeakCounts()
    if pix.size == 0:
        return pc
    for s0, _t, bins in iter_shot_chunks(path, settings.chunk_shots, start, stop):
        s1 = s0 + bins.shape[0]
        pc.add_keys(peak_window_keys(bins, theta[s0:s1], valid[s0:s1], table, pix,
                                     peaks["code_lo"], peaks["code_hi"], system.tdc.n_bins,
                                     peaks.get("step_lo"), peaks.get("step_hi")))
        if progress is not None:
            progress(s1 - s0)
    return pc.finished()


def points_from_counts(system: System, peaks: dict, counts: PeakCounts, settings: Settings,
                       shots_per_step=None):
    """The cloud: one fused point per peak from its counted detections.

    Each distinct (peak, step, code) is triangulated once at the step's grid
    angle (the angle it was classified with) and weighted by its count, times
    the probability that a detection at that step is signal when the peaks
    carry ``background_by_step`` (background subtraction in scan angle).
    Peaks whose stereo and ToF ranges disagree are left out
    (:func:`~mems_stereo.points.consistent_points`).
    ``shots_per_step`` : (S,) int, valid shots per angle step of the interval
    table (:func:`~mems_stereo.fastpath.shots_per_step`): with it the ToF and
    fused estimates are corrected for the first-photon delay
    (:class:`~mems_stereo.points.PeakAccumulator`).
    """
    from .points import points_from_peak_detections

    table = interval_table(system, settings.confidence, min_range=settings.min_range)
    S, nb = table.n_steps, system.tdc.n_bins + 1
    k = counts.keys
    q, step, code = k // (S * nb), (k // nb) % S, k % nb
    theta = table.theta_min + step * table.step
    weight = counts.counts.astype(np.float64)
    background = None
    bg = peaks.get("background_by_step")
    if bg is not None and k.size:
        # background subtraction in scan angle: the detections at a step are
        # signal with probability (n − expected background) / n; each entry
        # carries its share of the step's expected background (for the σ)
        qs = q * S + step
        n = np.bincount(qs, weights=weight)[qs]
        background = np.minimum(bg[q, step], n) * weight / n
        weight = weight * np.clip((n - bg[q, step]) / n, 0.0, 1.0)
    from .points import consistent_points

    cloud = points_from_peak_detections(system, np.arange(k.size), q, code, theta, peaks["row"],
                                        peaks["col"], peaks["code"],
                                        min_counts=settings.min_counts,
                                        confidence=settings.confidence, weight=weight,
                                        background=background,
                                        shots_per_step=shots_per_step,
                                        step_grid=(table.theta_min, table.step))
    return consistent_points(cloud, settings.confidence)


@dataclass
class ProcessResult:
    """Everything processing produced for one recording.

    histograms : dict of (H, W, n_bins) int64 ``raw``, ``signal``, ``noise``
        (index N−1 holds code N).
    background_hz : (H, W) float64, ML background rate per pixel from the noise
        histogram (pile-up aware).
    peaks : dict of (Q,) arrays ``row``, ``col``, ``code`` (peak code),
        ``code_lo``, ``code_hi`` (window), ``counts``.
    cloud : :class:`~mems_stereo.cloud.PointCloud`, one point per peak.
    counts : dict of integers (shots, unknown angle, raw, signal, noise).
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


def truth_scores(confusion: np.ndarray) -> dict:
    """Recall and noise rejection from a truth × assigned confusion matrix."""
    c = np.asarray(confusion)
    n_sig = c[1, 1] + c[1, 2]
    n_bg = c[2, 1] + c[2, 2]
    return {
        "true_signal": int(n_sig), "true_background": int(n_bg),
        "recall": float(c[1, 1] / n_sig) if n_sig else float("nan"),
        "noise_rejection": float(c[2, 2] / n_bg) if n_bg else float("nan"),
        "precision": float(c[1, 1] / (c[1, 1] + c[2, 1])) if (c[1, 1] + c[2, 1]) else
        float("nan"),
    }


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


def process_recording(path: str | os.PathLike, system: System | None = None,
                      settings: Settings | None = None, labels_path=None,
                      progress=None) -> ProcessResult:
    """Classify, histogram, find peaks and triangulate one recording (streamed).

    Parameters
    ----------
    path : FORMAT v1 recording (validated on read; see docs/formats.md).
    system : system to process with (default: the recording's ``/system``),
        e.g. a calibrated one.
    settings : :class:`Settings`.
    labels_path : write the event labels (FORMAT v1 outputs) there.
    progress : callable(n_shots_done) for progress bars.
    """
    st = Settings() if settings is None else settings
    t0 = time.perf_counter()
    header = read_header(path)
    sysm = header.system if system is None else system
    K, H, W = header.shape
    if (H, W) != (sysm.receiver.height, sysm.receiver.width):
        from .errors import FormatError

        raise FormatError(f"expected shape (K, {sysm.receiver.height}, {sysm.receiver.width}) "
                          f"of the processing system, found {header.shape}", str(path),
                          "/shots/bins")
    theta, valid = shot_angles(header, sysm)
    header.shot_time = None  # only the angles are needed from here on: free O(K) memory
    timings = {"read_header": time.perf_counter() - t0}

    t1 = time.perf_counter()
    if labels_path is not None:
        with _labels_file(labels_path, K, (H, W)) as (f, ds):
            acc = accumulate_range(path, sysm, theta, valid, st, labels_out=ds,
                                   progress=progress)
            f.create_dataset("theta", data=np.where(valid, theta, np.nan))
    else:
        acc = accumulate_range(path, sysm, theta, valid, st, progress=progress)
    timings["classify_histogram"] = time.perf_counter() - t1
    return finish_processing(path, sysm, header, theta, valid, acc, st, timings,
                             progress=progress)


def finish_processing(path, sysm, header, theta, valid, acc: RangeAccumulation, st: Settings,
                      timings: dict, count_peaks=None, progress=None) -> ProcessResult:
    """Peaks, background and points from the accumulated histograms.

    ``count_peaks(peaks) -> PeakCounts`` runs pass 2 over the whole recording
    (default: here, in chunks; the Dask runner passes its own).
    """
    from .peaks import find_peaks

    K, H, W = header.shape
    n_bins = sysm.tdc.n_bins
    t2 = time.perf_counter()
    raw = acc.hist_raw[:, 1:].reshape(H, W, n_bins)
    sig = acc.hist_signal[:, 1:].reshape(H, W, n_bins)
    noise = raw - sig
    peaks, background = find_peaks(sysm, sig, noise, theta, valid, st,
                                   signal_angle=acc.hist_angle)
    timings["peaks"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if count_peaks is None:
        counts = peak_counts_range(path, sysm, theta, valid, st, peaks, progress=progress)
    else:
        counts = count_peaks(peaks)
    timings["peak_detections"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    table = interval_table(sysm, st.confidence, min_range=st.min_range)
    cloud = points_from_counts(sysm, peaks, counts, st,
                               shots_per_step=shots_per_step(table, theta, valid))
    peaks.pop("background_by_step", None)  # (Q, S): used up; keep results light
    timings["points"] = time.perf_counter() - t4
    counts = {
        "shots": int(K), "shots_unknown_angle": int(acc.n_unknown),
        "raw": int(raw.sum()), "signal": int(sig.sum()), "noise": int(noise.sum()),
        "peaks": int(len(peaks["row"])), "points": len(cloud),
    }
    truth = truth_scores(acc.confusion) if acc.has_truth else None
    theta[~valid] = np.nan  # (already NaN where the angle is unknown; no copy)
    return ProcessResult(sysm, str(path), {"raw": raw, "signal": sig, "noise": noise},
                         background, peaks, cloud, counts, truth, theta, valid, timings)
