"""The processing chain of one recording, streamed in chunks of shots.

Two passes over ``/shots/bins``, each in chunks (memory does not grow with
the recording's length):

1. **classify and accumulate** (:func:`accumulate_range`): scan angle per
   shot from the zero crossings, labels from the compiled interval table
   (:mod:`mems_stereo.fastpath`, identical to the NumPy reference on the
   snapped angles), raw and signal histograms per pixel; optionally the
   labels file and, where the recording has ``/truth/label``, the confusion
   counts against the truth.
2. **peaks → points** (:func:`peak_pass_range`): after the peak detector
   has found each pixel's peak code window in the signal histogram, the
   signal detections inside the windows are streamed twice into a
   :class:`mems_stereo.points.PeakAccumulator` (the mode of each peak's
   ranges, then the sums over its inliers) and fused into one point per peak.

Every step is a function of a shot range and returns arrays that add up
(histograms, counts, peak accumulators), so the Dask runner
(:mod:`mems_stereo.distributed`) gets histograms and labels identical to one
process, and points equal up to the order of floating-point sums (1e-12).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import h5py
import numpy as np

from .classify import DEFAULT_CONFIDENCE
from .cloud import PointCloud
from .fastpath import classify_and_accumulate, interval_table
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
    false_alarm: float = 1e-2
    min_counts: int = 3


@dataclass
class RangeAccumulation:
    """What pass 1 returns for a shot range; sums over ranges with ``+``.

    hist_raw, hist_signal : (P, n_bins + 1) int64, column N = code N (column
        0: valid pixel-slots without detection).
    n_shots, n_unknown : shots in the range and those of unknown angle.
    confusion : (3, 3) int64, truth label (row) × assigned label (column),
        zeros when there is no truth.
    has_truth : bool.
    """

    hist_raw: np.ndarray
    hist_signal: np.ndarray
    n_shots: int
    n_unknown: int
    confusion: np.ndarray
    has_truth: bool

    def __add__(self, other: RangeAccumulation) -> RangeAccumulation:
        return RangeAccumulation(self.hist_raw + other.hist_raw,
                                 self.hist_signal + other.hist_signal,
                                 self.n_shots + other.n_shots, self.n_unknown + other.n_unknown,
                                 self.confusion + other.confusion,
                                 self.has_truth and other.has_truth)


def shot_angles(header, system: System):
    """(theta, valid) of every shot of a recording header, from its zero crossings."""
    return scan_angles(header.shot_time, header.zero_crossings, header.rising, system.scanner)


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
                                               want_labels=want)
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
    return RangeAccumulation(raw, sig, n_shots, n_unknown, conf, has_truth)


def _iter_peak_detections(path, system: System, theta, valid, settings: Settings,
                          peak_pixel, code_lo, code_hi, start: int = 0,
                          stop: int | None = None, progress=None):
    """Yield ``(shot, peak, code)`` (M,) int64 arrays per chunk: the signal detections
    inside the peak windows (``peak_pixel`` flat pixel index, inclusive windows)."""
    table = interval_table(system, settings.confidence, min_range=settings.min_range)
    n_bins = system.tdc.n_bins
    P = system.receiver.width * system.receiver.height
    pk = np.asarray(peak_pixel, dtype=np.int64)
    lo = np.asarray(code_lo, dtype=np.int64)
    hi = np.asarray(code_hi, dtype=np.int64)
    if pk.size == 0:
        return
    raw32 = np.zeros((P, n_bins + 1), np.int32)
    sig32 = np.zeros((P, n_bins + 1), np.int32)
    for s0, _t, bins, in iter_shot_chunks(path, settings.chunk_shots, start, stop):
        s1 = s0 + bins.shape[0]
        labels, _, _ = classify_and_accumulate(bins, theta[s0:s1], valid[s0:s1], table, n_bins,
                                               raw32, sig32)
        b2 = bins.reshape(bins.shape[0], P)[:, pk].astype(np.int64)  # (k, Q)
        l2 = labels.reshape(bins.shape[0], P)[:, pk]
        kk, qq = np.nonzero((l2 == 1) & (b2 >= lo) & (b2 <= hi))
        yield kk + s0, qq, b2[kk, qq]
        if progress is not None:
            progress(s1 - s0)


def peak_pass_range(path, system: System, theta, valid, settings: Settings, peaks: dict,
                    template, kind: str, start: int = 0, stop: int | None = None,
                    progress=None):
    """Pass 2 over shots [start, stop): feed the peak windows' signal detections to a
    :class:`~mems_stereo.points.PeakAccumulator` (``kind`` "mode" or "inliers").

    ``template`` is copied empty (keeping its centres); the filled copy is
    returned, to be added to the other ranges' copies.
    """
    acc = template.empty_copy()
    add = acc.add_mode if kind == "mode" else acc.add_inliers
    W = system.receiver.width
    th = np.where(valid, theta, 0.0)
    for shot, q, code in _iter_peak_detections(path, system, theta, valid, settings,
                                               peaks["row"] * W + peaks["col"],
                                               peaks["code_lo"], peaks["code_hi"], start, stop,
                                               progress):
        add(shot, q, code, th)
    return acc


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
                      timings: dict, run_pass=None, progress=None) -> ProcessResult:
    """Peaks, background and points from the accumulated histograms.

    ``run_pass(kind, template) -> PeakAccumulator`` runs one sub-pass of pass
    2 over the whole recording (default: here, in chunks; the Dask runner
    passes its own).
    """
    from .peaks import find_peaks
    from .points import PeakAccumulator

    K, H, W = header.shape
    n_bins = sysm.tdc.n_bins
    t2 = time.perf_counter()
    raw = acc.hist_raw[:, 1:].reshape(H, W, n_bins)
    sig = acc.hist_signal[:, 1:].reshape(H, W, n_bins)
    noise = raw - sig
    peaks, background = find_peaks(sysm, sig, noise, theta, valid, st)
    timings["peaks"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if run_pass is None:
        def run_pass(kind, template):
            return peak_pass_range(path, sysm, theta, valid, st, peaks, template, kind,
                                   progress=progress)
    template = PeakAccumulator(sysm, peaks["row"], peaks["col"], peaks["code"],
                               confidence=st.confidence)
    mode = run_pass("mode", template)
    mode.finish_mode()
    sums = run_pass("inliers", mode)
    cloud = sums.cloud(st.min_counts)
    timings["points"] = time.perf_counter() - t3
    counts = {
        "shots": int(K), "shots_unknown_angle": int(acc.n_unknown),
        "raw": int(raw.sum()), "signal": int(sig.sum()), "noise": int(noise.sum()),
        "peaks": int(len(peaks["row"])), "points": len(cloud),
    }
    truth = truth_scores(acc.confusion) if acc.has_truth else None
    return ProcessResult(sysm, str(path), {"raw": raw, "signal": sig, "noise": noise},
                         background, peaks, cloud, counts, truth,
                         np.where(valid, theta, np.nan), valid, timings)
