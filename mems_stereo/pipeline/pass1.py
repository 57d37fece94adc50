"""Pass 1: classify every detection and accumulate raw/signal/noise histograms.

The compiled kernel looks each shot's accepted code interval up in the
:class:`~mems_stereo.pipeline.intervals.IntervalTable`; the pure-Python
kernels beside it are its reference semantics (used when numba is absent).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mems_stereo.io.recording import iter_shot_chunks
from mems_stereo.model.system import System
from mems_stereo.pipeline.intervals import IntervalTable, interval_table
from mems_stereo.pipeline.settings import Settings

# --------------------------------------------------------------------------
# compiled kernel


def _kernel_py(bins, rows, lo, hi, labels, hist_raw, hist_signal, hist_angle):
    """Reference semantics of the compiled kernel (pure Python; used when numba is absent).

    bins : (K, P) uint16, codes <= n_bins (checked by the caller: the kernel
    does no bounds checks); rows : (K,) int64 table row (−1: shot left out,
    label 0, not counted); lo, hi : (S, P) uint16; labels : (K, P) uint8 out;
    hist_raw, hist_signal : (P, n_bins + 1) int32 added to in place (column N
    counts code N; column 0 of ``hist_raw`` counts the slots without a
    detection); hist_angle : (P, S) int64, signal detections per pixel and
    angle step, added to in place.  Codes are cast to int64 before any arithmetic (numba would
    otherwise mix unsigned and signed integers through float64); the loop
    body has a single data-dependent branch (the rare signal count).
    """
    K, P = bins.shape
    for k in range(K):
        j = rows[k]
        if j < 0:
            for p in range(P):
                labels[k, p] = 0
            continue
        for p in range(P):
            c = np.int64(bins[k, p])
            hist_raw[p, c] += 1
            ok = (c != 0) & (np.int64(lo[j, p]) <= c) & (c <= np.int64(hi[j, p]))
            if ok:
                hist_signal[p, c] += 1
                hist_angle[p, j] += 1
            labels[k, p] = (c != 0) * (2 - ok)


def _kernel_nolabels_py(bins, rows, lo, hi, hist_raw, hist_signal, hist_angle):
    """As :func:`_kernel_py` without writing labels."""
    K, P = bins.shape
    for k in range(K):
        j = rows[k]
        if j < 0:
            continue
        for p in range(P):
            c = np.int64(bins[k, p])
            hist_raw[p, c] += 1
            if (c != 0) & (np.int64(lo[j, p]) <= c) & (c <= np.int64(hi[j, p])):
                hist_signal[p, c] += 1
                hist_angle[p, j] += 1


try:  # pragma: no cover - exercised whenever numba is installed (a declared dependency)
    import numba

    _jit = numba.njit(cache=True, nogil=True, boundscheck=False)
    _kernel = _jit(_kernel_py)
    _kernel_nolabels = _jit(_kernel_nolabels_py)
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    _kernel, _kernel_nolabels = _kernel_py, _kernel_nolabels_py
    HAVE_NUMBA = False


def classify_and_accumulate(bins, theta, valid, table: IntervalTable, n_bins: int,
                            hist_raw=None, hist_signal=None, want_labels: bool = True,
                            hist_angle=None):
    """Label a block of shots and add it to the raw and signal histograms.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes.
    theta : (K,) rad; valid : (K,) bool (False: shot left out, label 0,
        not counted).
    table : :class:`IntervalTable` of the system (rows filled on demand).
    n_bins : codes above it raise :class:`~mems_stereo.errors.FormatError`.
    hist_raw, hist_signal : (H*W, n_bins + 1) int32, added to in place
        (allocated when None).  Column N counts code N; column 0 of
        ``hist_raw`` counts valid pixel-slots without a detection.  The noise
        histogram is ``hist_raw − hist_signal`` (columns 1..n_bins).
    want_labels : return the (K, H, W) uint8 labels (else None).
    hist_angle : (H*W, S) int64, signal detections per pixel and angle step of
        ``table``, added to in place (allocated when None).

    Returns
    -------
    labels, hist_raw, hist_signal (and hist_angle is filled in place).
    """
    b = np.ascontiguousarray(bins)
    if b.dtype != np.uint16:
        b = b.astype(np.uint16)
    K = b.shape[0]
    P = int(np.prod(b.shape[1:]))
    b2 = b.reshape(K, P)
    if b2.size and int(b2.max()) > n_bins:  # the kernel indexes without bounds checks
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected codes 0..{n_bins}, found {int(b2.max())}", field="bins")
    rows = table.index(theta)
    rows[~np.asarray(valid, dtype=bool)] = -1
    table.ensure(rows)
    if hist_raw is None:
        hist_raw = np.zeros((P, n_bins + 1), dtype=np.int32)
    if hist_signal is None:
        hist_signal = np.zeros((P, n_bins + 1), dtype=np.int32)
    if hist_angle is None:
        hist_angle = np.zeros((P, table.n_steps), dtype=np.int64)
    if want_labels:
        labels = np.empty((K, P), dtype=np.uint8)
        _kernel(b2, rows, table.lo, table.hi, labels, hist_raw, hist_signal, hist_angle)
    else:
        labels = None
        _kernel_nolabels(b2, rows, table.lo, table.hi, hist_raw, hist_signal, hist_angle)
    return (labels.reshape(b.shape) if want_labels else None), hist_raw, hist_signal


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


# --------------------------------------------------------------------------
# counts and the whole-recording classification

#: legacy keys of ``classify_recording``'s counts (version 0.1) → the names of :class:`Counts`
_LEGACY_KEYS = {"n_shots": "shots", "n_shots_unknown_angle": "shots_unknown_angle",
                "n_detections": "raw", "n_signal": "signal", "n_noise": "noise"}


@dataclass(frozen=True)
class Counts(Mapping):
    """The counts of one classified or processed recording (integers).

    shots : shots in the recording; shots_unknown_angle : those outside the
    zero crossings' span (left out, label 0); raw : detections in the other
    shots; signal, noise : how they were classified (raw = signal + noise);
    peaks, points : found by processing (None after classification alone).

    Read it as a mapping too (``counts["signal"]``, ``dict(counts)``); the
    keys are the same for :func:`classify_recording` and
    :func:`~mems_stereo.pipeline.run.process_recording`, and on the same
    recording and settings the numbers are the same.
    """

    shots: int
    shots_unknown_angle: int
    raw: int
    signal: int
    noise: int
    peaks: int | None = None
    points: int | None = None

    def __getitem__(self, key):
        name = _LEGACY_KEYS.get(key, key)
        if name not in self.__dataclass_fields__:
            raise KeyError(key)
        return getattr(self, name)

    def __iter__(self):
        return iter(self.__dataclass_fields__)

    def __len__(self) -> int:
        return len(self.__dataclass_fields__)

    def __repr__(self) -> str:
        return "Counts(" + ", ".join(f"{k}={v}" for k, v in self.items()
                                     if v is not None) + ")"

    @classmethod
    def from_accumulation(cls, acc: RangeAccumulation, peaks: int | None = None,
                          points: int | None = None) -> Counts:
        raw = int(acc.hist_raw[:, 1:].sum())
        sig = int(acc.hist_signal[:, 1:].sum())
        return cls(int(acc.n_shots), int(acc.n_unknown), raw, sig, raw - sig, peaks, points)


def classify_recording(recording, system: System | None = None,
                       confidence: float | None = None, min_range: float | None = None,
                       settings: Settings | None = None):
    """Classify every detection of a recording, as processing does.

    Parameters
    ----------
    recording : a :class:`~mems_stereo.io.recording.Recording` or the path of
        a FORMAT v1 file.
    system : the system to classify with (default: the recording's ``/system``).
    confidence, min_range : override those of ``settings`` (default
        :class:`Settings`).

    Returns
    -------
    :class:`~mems_stereo.pipeline.consistency.ClassificationResult`:
    ``labels`` (K, H, W) uint8 (0 none / unknown angle, 1 signal, 2 noise),
    ``theta`` (K,) rad (NaN where unknown), ``valid`` (K,) bool, ``counts``
    (:class:`Counts`, the same as ``process_recording``'s), ``truth``
    (recall and rejection against ``/truth/label``, or None).

    It uses the compiled interval table of
    :func:`~mems_stereo.pipeline.run.process_recording`, so both label every
    detection alike.  :func:`~mems_stereo.pipeline.consistency.classify_bins`
    is the reference on exact (not step-snapped) angles; the two differ on
    about one detection in 10⁴ (room.h5: 1 of 19 476), at the edge of a window.
    """
    import dataclasses

    from mems_stereo.io.recording import Recording, read_header
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.consistency import ClassificationResult

    st = Settings() if settings is None else settings
    if confidence is not None:
        st = dataclasses.replace(st, confidence=confidence)
    if min_range is not None:
        st = dataclasses.replace(st, min_range=min_range)
    src = recording if isinstance(recording, Recording) else str(recording)
    header = read_header(src)
    sysm = header.system if system is None else system
    theta, valid = shot_angles(header, sysm)
    labels = np.zeros(header.shape, np.uint8)
    acc = accumulate_range(src, sysm, theta, valid, st, labels_out=labels)
    res = ClassificationResult(labels, np.where(valid, theta, np.nan), valid,
                               Counts.from_accumulation(acc), st.confidence)
    res.truth = truth_scores(acc.confusion) if acc.has_truth else None
    return res


def truth_scores(confusion: np.ndarray) -> dict:
    """Recall and noise rejection from a (3, 3) truth (row) × assigned (column) confusion matrix."""
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
