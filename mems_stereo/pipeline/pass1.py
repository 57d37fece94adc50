"""Pass 1: classify every detection and accumulate raw/signal/noise histograms.

The compiled kernel looks each shot's accepted code interval up in the
:class:`~mems_stereo.pipeline.intervals.IntervalTable`; the pure-Python
kernels beside it are its reference semantics (used when numba is absent).
"""

from __future__ import annotations

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
