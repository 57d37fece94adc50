"""Pass 1: classify every detection and accumulate raw/signal/noise histograms.

:func:`accumulate_range` runs the kernel of
:mod:`~mems_stereo.pipeline.classify_kernel` over the chunks of a range of shots;
:func:`classify_recording` labels a whole recording as processing does.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mems_stereo.io.recording import iter_shot_chunks, read_system
from mems_stereo.model.system import System
from mems_stereo.pipeline.classify_kernel import (
    COMPILE_SLOTS,
    RAW16_SHOTS,
    KernelOptions,
    Pass1Histograms,
    classify_and_accumulate,
    compiles,
)
from mems_stereo.pipeline.consistency import DEFAULT_CONFIDENCE, truth_suffix
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange
from mems_stereo.util.packing import pack_sparse, unpack_sparse

#: counts of a shot range fit in uint32 while the range has fewer shots than this
UINT32_SHOTS = 1 << 32


def _count_dtype(n_shots: int):
    """uint32 while every count of ``n_shots`` shots fits, else int64."""
    return np.uint32 if n_shots < UINT32_SHOTS else np.int64


_COUNT_FIELDS = ("hist_raw", "hist_signal", "hist_angle")


@dataclass
class RangeAccumulation:
    """What pass 1 returns for a shot range; sums over ranges with ``+``.

    Attributes
    ----------
    hist_raw, hist_signal : (P, n_bins + 1) uint32 (int64 once a sum holds
        2³² shots or more), column N = code N (column 0: valid pixel-slots
        without detection).
    hist_angle : (P, S) uint32 (likewise), signal detections per pixel and
        scan-angle step of the interval table.
    n_per_step : (S,) int64, valid shots classified with each angle step.
    n_shots, n_unknown : shots in the range and those of unknown angle.
    confusion : (3, 3) int64, truth label (row) × assigned label (column),
        zeros when there is no truth.
    has_truth : bool.

    Notes
    -----
    Every field is an exact integer sum, so parts add in any order to the
    whole; pickled (Dask), the count arrays travel as their non-zero entries
    when that is smaller.
    """

    hist_raw: np.ndarray
    hist_signal: np.ndarray
    hist_angle: np.ndarray
    n_per_step: np.ndarray
    n_shots: int
    n_unknown: int
    confusion: np.ndarray
    has_truth: bool

    def __add__(self, other: RangeAccumulation) -> RangeAccumulation:
        n = self.n_shots + other.n_shots
        dt = np.result_type(_count_dtype(n), self.hist_raw.dtype, other.hist_raw.dtype)

        def add(a, b):
            return np.add(a, b, dtype=dt)

        return RangeAccumulation(add(self.hist_raw, other.hist_raw),
                                 add(self.hist_signal, other.hist_signal),
                                 add(self.hist_angle, other.hist_angle),
                                 self.n_per_step + other.n_per_step,
                                 n, self.n_unknown + other.n_unknown,
                                 self.confusion + other.confusion,
                                 self.has_truth and other.has_truth)

    def __getstate__(self):
        d = dict(self.__dict__)
        for k in _COUNT_FIELDS:
            d[k] = pack_sparse(d[k])
        return d

    def __setstate__(self, d):
        for k in _COUNT_FIELDS:
            d[k] = unpack_sparse(d[k])
        self.__dict__.update(d)


def sum_accumulations(parts) -> RangeAccumulation:
    """The sum of pass-1 results (exact integers: any order, any grouping)."""
    parts = list(parts)
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total


def accumulate_range(path, system: System, shots: ShotRange, settings: Settings,
                     labels_out=None, progress=None, table: IntervalTable | None = None,
                     signal_store=None) -> RangeAccumulation:
    """Pass 1 over the shots of ``shots``: labels and histograms.

    ``labels_out`` : an h5py dataset (K, H, W) uint8 to write labels into, or None.
    ``progress(n)`` : called after each chunk of n shots.
    ``table`` : the run's :class:`IntervalTable` (rows filled here as needed;
    default: a new one from ``settings``).
    ``signal_store`` : a :class:`~mems_stereo.pipeline.signal_store.SignalStore` to
    keep the signal detections in for pass 2 (compiled ranges only: it is
    marked incomplete, and stays empty, for small ones).
    """
    P = system.receiver.width * system.receiver.height
    n_bins = system.tdc.n_bins
    if table is None:
        table = IntervalTable.for_settings(system, settings)
    K_range = max(0, shots.n_shots)
    compiled = compiles(K_range * P, COMPILE_SLOTS)  # small recordings: NumPy (not in frames)
    # the reader checks codes against the file's n_bins: enough when it is ours too;
    # otherwise each chunk is checked below (naming the file), not again in the kernel call
    file_bins = read_system(path).tdc.n_bins
    hists = Pass1Histograms.zeros(P, n_bins, table.n_steps, _count_dtype(K_range))
    tally = _RangeTally(table.n_steps)
    raw16 = _Raw16Table(hists, compiled)
    keys_buf = None
    for s0, _t, bins, truth in iter_shot_chunks(path, settings.chunk_shots, shots.start,
                                                shots.stop, truth_labels=True):
        s1 = s0 + bins.shape[0]
        raw16.before_chunk(s1 - s0)
        if compiled and signal_store is not None and (
                keys_buf is None or keys_buf.size < bins.size):
            keys_buf = np.empty(bins.size, np.int64)
        th, v = shots.angles(s0, s1)
        rows = table.rows(th, v)
        if file_bins > n_bins:
            _check_codes(bins, n_bins, file_bins, s0, s1, path)
        keys = [] if signal_store is not None and compiled else None
        want = labels_out is not None or truth is not None
        labels, _ = classify_and_accumulate(
            bins, th, v, table, n_bins, hists, want_labels=want, rows=rows,
            options=KernelOptions(compiled, True, keys, raw16.scratch(s1 - s0), keys_buf))
        raw16.after_chunk(s1 - s0)
        if signal_store is not None:
            if keys:
                signal_store.append(keys[0])
            else:
                signal_store.complete = False
        if labels_out is not None:
            labels_out[s0:s1] = labels
        tally.add(s1 - s0, rows, v, truth, labels)
        if progress is not None:
            progress(s1 - s0)
    raw16.flush()
    return RangeAccumulation(hists.raw, hists.signal, hists.angle, tally.n_per_step,
                             tally.n_shots, tally.n_unknown, tally.confusion, tally.has_truth)


def _check_codes(bins, n_bins: int, file_bins: int, s0: int, s1: int, path) -> None:
    """Raise :class:`~mems_stereo.errors.FormatError` when a code of shots ``s0..s1−1``
    exceeds the ``n_bins`` of the system used (the recording's own has ``file_bins``)."""
    if bins.size and int(bins.max()) > n_bins:
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected codes 0..{n_bins} (tdc.n_bins of the system used), "
                          f"found {int(bins.max())} in shots {s0}..{s1 - 1} (the "
                          f"recording's own system has n_bins = {file_bins})",
                          str(getattr(path, "source", path)), "/shots/bins")


class _RangeTally:
    """The per-shot sums of :func:`accumulate_range`: valid shots per angle step,
    shots, those of unknown angle, and the truth × label confusion."""

    def __init__(self, n_steps: int):
        self.n_steps = n_steps
        self.n_per_step = np.zeros(n_steps, np.int64)
        self.confusion = np.zeros((3, 3), np.int64)
        self.has_truth = True
        self.n_shots = self.n_unknown = 0

    def add(self, n: int, rows, valid, truth, labels) -> None:
        """Add a chunk of ``n`` shots: their table ``rows``, ``valid``, ``truth`` labels (None: no
        truth) and assigned ``labels``."""
        self.n_per_step += np.bincount(rows[rows >= 0], minlength=self.n_steps)
        if truth is None:
            self.has_truth = False
        else:
            tl = np.asarray(truth, dtype=np.int64)
            self.confusion += np.bincount((tl * 3 + labels).ravel(),
                                          minlength=9).reshape(3, 3)
        self.n_shots += n
        self.n_unknown += int(np.count_nonzero(~valid))


class _Raw16Table:
    """The uint16 table that the compiled kernel counts raw codes into (half the size of
    a uint32 one: it stays in the cache more), added to ``hists.raw`` every
    :data:`RAW16_SHOTS` shots (no cell can overflow before); none on the NumPy path."""

    def __init__(self, hists: Pass1Histograms, compiled: bool):
        self.hists = hists
        self.table = np.zeros(hists.raw.shape, np.uint16) if compiled else None
        self.held = 0

    def before_chunk(self, n: int) -> None:
        """Flush the table when a chunk of ``n`` shots could overflow it."""
        if self.table is not None and self.held + n >= RAW16_SHOTS:
            self.hists.raw += self.table
            self.table[:] = 0
            self.held = 0

    def scratch(self, n: int):
        """The table for a chunk of ``n`` shots (None: counted straight into ``raw``)."""
        return self.table if n < RAW16_SHOTS else None

    def after_chunk(self, n: int) -> None:
        if self.table is not None and n < RAW16_SHOTS:
            self.held += n

    def flush(self) -> None:
        if self.table is not None and self.held:
            self.hists.raw += self.table


# --------------------------------------------------------------------------
# counts and the whole-recording classification

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
        if key not in self.__dataclass_fields__:
            raise KeyError(key)
        return getattr(self, key)

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


@dataclass
class ClassificationResult:
    """Labels of a recording and the counts (:func:`classify_recording`).

    labels : (K, H, W) uint8 (0 none / unknown angle, 1 signal, 2 noise);
    theta : (K,) float64 rad (NaN where unknown); valid : (K,) bool;
    counts : :class:`Counts` (shots, shots_unknown_angle, raw, signal, noise);
    confidence : float; truth : recall and noise rejection against
    ``/truth/label`` (:func:`truth_scores`; None without truth).
    """

    labels: np.ndarray
    theta: np.ndarray
    valid: np.ndarray
    counts: Counts
    confidence: float = DEFAULT_CONFIDENCE
    truth: dict | None = None

    def __repr__(self) -> str:
        c = self.counts
        return (f"<ClassificationResult {c.shots} shots, {c.raw} detections: "
                f"{c.signal} signal, {c.noise} noise{truth_suffix(self.truth)}>")


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
    :class:`ClassificationResult`:
    ``labels`` (K, H, W) uint8 (0 none / unknown angle, 1 signal, 2 noise),
    ``theta`` (K,) rad (NaN where unknown), ``valid`` (K,) bool, ``counts``
    (:class:`Counts`, the same as ``process_recording``'s), ``truth``
    (recall and rejection against ``/truth/label``, or None).

    It uses the compiled interval table of
    :func:`~mems_stereo.pipeline.run.process_recording`, so both label every
    detection alike.  :func:`~mems_stereo.pipeline.consistency.classify_bins`
    is the reference on exact (not step-snapped) angles; the two differ on
    about one detection in 10⁴, at the edge of a window.

    Examples
    --------
    >>> result = ms.classify_recording(ms.data.path("room.h5"))
    >>> result.labels.shape
    (800, 1, 192)
    >>> int((result.labels == 1).sum()), int((result.labels == 2).sum())     # signal, noise
    (1295, 18223)
    """
    import dataclasses

    from mems_stereo.io.recording import Recording, read_header
    from mems_stereo.pipeline.angles import shot_angles

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
    acc = accumulate_range(src, sysm, ShotRange(theta, valid), st, labels_out=labels)
    return ClassificationResult(labels, np.where(valid, theta, np.nan), valid,
                                Counts.from_accumulation(acc), st.confidence,
                                truth_scores(acc.confusion) if acc.has_truth else None)


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
