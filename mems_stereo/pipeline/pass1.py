"""Pass 1: classify every detection and accumulate raw/signal/noise histograms.

The compiled kernel looks each shot's accepted code interval up in the
:class:`~mems_stereo.pipeline.intervals.IntervalTable`; the pure-Python
kernels beside it are its reference semantics; small recordings use the same
semantics in vectorised NumPy, so that they never load compiled code.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mems_stereo.io.recording import iter_shot_chunks, read_system
from mems_stereo.model.system import System
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.settings import Settings

#: counts of a shot range fit in uint32 while the range has fewer shots than this
UINT32_SHOTS = 1 << 32

# --------------------------------------------------------------------------
# compiled kernel


def _kernel_py(bins, rows, lo, hi, labels, hist_raw, hist_signal, hist_angle):
    """Reference semantics of the compiled kernel (pure Python; used when numba is absent).

    bins : (K, P) uint16, codes <= n_bins (checked by the caller: the kernel
    does no bounds checks); rows : (K,) int64 table row (−1: shot left out,
    label 0, not counted); lo, hi : (S, P) uint16; labels : (K, P) uint8 out;
    hist_raw, hist_signal : (P, n_bins + 1) integer (uint32 in the pipeline)
    added to in place (column N counts code N; column 0 of ``hist_raw`` counts
    the slots without a detection); hist_angle : (P, S) integer (uint32),
    signal detections per pixel and angle step, added to in place.  Codes
    are cast to int64 before any arithmetic (numba would otherwise mix
    unsigned and signed integers through float64); the loop body has a
    single data-dependent branch (the rare signal count).
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


def _kernel_keys_py(bins, rows, lo, hi, hist_raw, hist_signal, hist_angle, shift_j, shift_p,
                    keys):
    """As :func:`_kernel_nolabels_py`, also writing the key
    ``p << shift_p | j << shift_j | c`` of every signal detection (pixel p, angle
    step j, code c; :func:`signal_key_shifts`) to ``keys`` (room for K·P); returns
    how many (see :func:`signal_keys`)."""
    K, P = bins.shape
    n = 0
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
                keys[n] = (np.int64(p) << shift_p) | (j << shift_j) | c
                n += 1
    return n


def signal_key_shifts(n_steps: int, nb: int) -> tuple[int, int]:
    """``(shift_j, shift_p)`` of the signal keys ``p << shift_p | j << shift_j | c``
    (pixel p, angle step j < ``n_steps``, code c < ``nb``): bit fields, so that
    pass 2 reads a key's pixel, step and code with shifts and masks (no integer
    division: 1.8x faster over a dense recording's 32 M stored keys)."""
    shift_j = max(1, int(nb - 1).bit_length())
    return shift_j, shift_j + max(1, int(n_steps - 1).bit_length())


def encode_signal_keys(p, j, c, n_steps: int, nb: int) -> np.ndarray:
    """The signal keys (int64) of pixels ``p``, angle steps ``j`` and codes ``c``
    (:func:`signal_key_shifts`)."""
    sj, sp = signal_key_shifts(n_steps, nb)
    return ((np.asarray(p, np.int64) << sp) | (np.asarray(j, np.int64) << sj)
            | np.asarray(c, np.int64))


def decode_signal_keys(keys, n_steps: int, nb: int):
    """``(p, j, c)`` (int64) of signal keys (:func:`encode_signal_keys`)."""
    sj, sp = signal_key_shifts(n_steps, nb)
    k = np.asarray(keys, np.int64)
    return k >> sp, (k >> sj) & ((1 << (sp - sj)) - 1), k & ((1 << sj) - 1)


def signal_keys(bins, rows, labels, n_steps: int, nb: int) -> np.ndarray:
    """Keys (:func:`encode_signal_keys`, int64, in shot order) of the detections
    labelled signal: ``bins`` (K, P) codes, ``rows`` (K,) angle steps, ``labels``
    (K, P) (1 = signal); the same keys as :func:`_kernel_keys_py` writes."""
    k, p = np.nonzero(np.asarray(labels).reshape(bins.shape) == 1)
    return encode_signal_keys(p, rows[k], bins[k, p], n_steps, nb)


def _kernel_numpy(bins, rows, lo, hi, labels, hist_raw, hist_signal, hist_angle):
    """The kernel's semantics in vectorised NumPy (``labels`` None: not written).

    For small blocks: no compiled code to load (numba's first call costs
    about half a second); identical counts and labels (integers).
    """
    K, P = bins.shape
    use = rows >= 0
    r = rows[use]
    c = bins[use].astype(np.int64)
    nb1 = hist_raw.shape[1]
    ok = (c != 0) & (lo[r] <= c) & (c <= hi[r])
    key = np.arange(P, dtype=np.int64)[None, :] * nb1 + c
    np.add(hist_raw, np.bincount(key.ravel(), minlength=P * nb1).reshape(P, nb1),
           out=hist_raw, casting="unsafe")
    np.add(hist_signal, np.bincount(key[ok], minlength=P * nb1).reshape(P, nb1),
           out=hist_signal, casting="unsafe")
    pk, pp = np.nonzero(ok)
    np.add.at(hist_angle, (pp, r[pk]), 1)
    if labels is not None:
        labels[~use] = 0
        labels[use] = (c != 0) * (2 - ok.astype(np.int64))


#: blocks of fewer pixel-slots than this are classified with NumPy (no numba load)
COMPILE_SLOTS = 1 << 21

_COMPILED: dict = {}


def _compiled():
    """The numba kernels ``(labels, no labels, signal keys)``, compiled (or loaded from numba's
    disk cache) on first use; None when numba is absent."""
    if "k" not in _COMPILED:
        try:  # pragma: no cover - numba is a declared dependency
            import numba

            jit = numba.njit(cache=True, nogil=True, boundscheck=False)
            _COMPILED["k"] = (jit(_kernel_py), jit(_kernel_nolabels_py),
                              jit(_kernel_keys_py))
        except ImportError:  # pragma: no cover
            _COMPILED["k"] = None
    return _COMPILED["k"]


def classify_and_accumulate(bins, theta, valid, table: IntervalTable, n_bins: int,
                            hist_raw=None, hist_signal=None, want_labels: bool = True,
                            hist_angle=None, rows=None, compiled: bool | None = None,
                            codes_checked: bool = False, keys_out=None, raw_scratch=None,
                            keys_scratch=None):
    """Label a block of shots and add it to the raw and signal histograms.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes.
    theta : (K,) rad; valid : (K,) bool (False: shot left out, label 0,
        not counted).
    table : :class:`IntervalTable` of the system (rows filled on demand).
    n_bins : codes above it raise :class:`~mems_stereo.errors.FormatError`.
    hist_raw, hist_signal : (H*W, n_bins + 1) integer counts, added to in
        place (uint32 allocated when None).  Column N counts code N; column 0
        of ``hist_raw`` counts valid pixel-slots without a detection.  The
        noise histogram is ``hist_raw − hist_signal`` (columns 1..n_bins).
    want_labels : return the (K, H, W) uint8 labels (else None).
    hist_angle : (H*W, S) integer, signal detections per pixel and angle step
        of ``table``, added to in place (uint32 allocated when None).
    rows : (K,) int64 table rows of the shots (:meth:`IntervalTable.rows`),
        when the caller has them already.
    compiled : True: the numba kernel; False: the same in NumPy; None (default):
        numba for blocks of at least :data:`COMPILE_SLOTS` pixel-slots.
    codes_checked : the caller has checked every code <= n_bins already
        (:func:`~mems_stereo.io.recording.iter_shot_chunks` does).
    keys_out : a list to append the block's signal keys to (:func:`signal_keys`:
        (pixel, angle step, code), int64), for pass 2 to count from instead of
        reading the shots again; only on the compiled path (the list is left
        untouched otherwise, and the caller reads the shots).
    raw_scratch : a (H*W, n_bins + 1) uint16 table that the compiled kernel counts
        the raw codes into instead of ``hist_raw`` (left untouched); the caller adds
        it to ``hist_raw`` before it could hold 2**16 shots (:func:`accumulate_range`
        does, every :data:`RAW16_SHOTS` shots).  Ignored on the NumPy path.
    keys_scratch : an int64 buffer of at least K*H*W that the compiled kernel writes
        the signal keys into before they are copied to ``keys_out`` (reused between
        blocks: no fresh buffer of 8 bytes a pixel-slot per block).

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
    if not codes_checked and b2.size and int(b2.max()) > n_bins:  # kernel: no bounds checks
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected codes 0..{n_bins}, found {int(b2.max())}", field="bins")
    if rows is None:
        rows = table.rows(theta, valid)
    table.ensure(rows)
    if hist_raw is None:
        hist_raw = np.zeros((P, n_bins + 1), dtype=np.uint32)
    if hist_signal is None:
        hist_signal = np.zeros((P, n_bins + 1), dtype=np.uint32)
    if hist_angle is None:
        hist_angle = np.zeros((P, table.n_steps), dtype=np.uint32)
    labels = np.empty((K, P), dtype=np.uint8) if want_labels else None
    if compiled is None:
        compiled = b2.size >= COMPILE_SLOTS
    kernels = _compiled() if compiled else None
    if kernels is None:
        _kernel_numpy(b2, rows, table.lo, table.hi, labels, hist_raw, hist_signal, hist_angle)
        return (labels.reshape(b.shape) if want_labels else None), hist_raw, hist_signal
    # the compiled kernels count every slot into the raw histogram at a random code:
    # a block of fewer than 2**16 shots counts into a uint16 table of half the size
    # (it stays in the cache more: ~17 % less kernel time on a dense recording),
    # added to hist_raw after (exact: no cell can count more than the block's shots)
    if raw_scratch is not None:
        raw = raw_scratch
    else:
        raw = np.zeros(hist_raw.shape, np.uint16) if K < RAW16_SHOTS else hist_raw
    if want_labels:
        kernels[0](b2, rows, table.lo, table.hi, labels, raw, hist_signal, hist_angle)
        if keys_out is not None:
            keys_out.append(signal_keys(b2, rows, labels, table.n_steps, n_bins + 1))
    elif keys_out is not None:
        buf = (keys_scratch if keys_scratch is not None and keys_scratch.size >= b2.size
               else np.empty(b2.size, np.int64))
        n = kernels[2](b2, rows, table.lo, table.hi, raw, hist_signal, hist_angle,
                       *signal_key_shifts(table.n_steps, n_bins + 1), buf)
        keys_out.append(buf[:n].copy())
    else:
        kernels[1](b2, rows, table.lo, table.hi, raw, hist_signal, hist_angle)
    if raw is not hist_raw and raw is not raw_scratch:
        hist_raw += raw
    return (labels.reshape(b.shape) if want_labels else None), hist_raw, hist_signal


#: blocks of fewer shots than this count their raw histogram in uint16 first
#: (:func:`classify_and_accumulate`)
RAW16_SHOTS = 1 << 16


def _count_dtype(n_shots: int):
    """uint32 while every count of ``n_shots`` shots fits, else int64."""
    return np.uint32 if n_shots < UINT32_SHOTS else np.int64


# compact transfer of a part's counts between processes (Dask): a count array is
# pickled as its non-zero entries when that is smaller than the dense array
def _pack(a: np.ndarray):
    nz = np.flatnonzero(a)
    if nz.size * (4 + a.itemsize) < a.nbytes and a.size < (1 << 32):
        return ("sparse", a.shape, a.dtype.str, nz.astype(np.uint32), a.ravel()[nz])
    return ("dense", a)


def _unpack(x) -> np.ndarray:
    if x[0] == "dense":
        return x[1]
    _, shape, dtype, idx, values = x
    a = np.zeros(int(np.prod(shape)), dtype=np.dtype(dtype))
    a[idx] = values
    return a.reshape(shape)


_COUNT_FIELDS = ("hist_raw", "hist_signal", "hist_angle")


@dataclass
class RangeAccumulation:
    """What pass 1 returns for a shot range; sums over ranges with ``+``.

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
            d[k] = _pack(d[k])
        return d

    def __setstate__(self, d):
        for k in _COUNT_FIELDS:
            d[k] = _unpack(d[k])
        self.__dict__.update(d)


def sum_accumulations(parts) -> RangeAccumulation:
    """The sum of pass-1 results (exact integers: any order, any grouping)."""
    parts = list(parts)
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total


def accumulate_range(path, system: System, theta, valid, settings: Settings,
                     start: int = 0, stop: int | None = None, labels_out=None,
                     progress=None, table: IntervalTable | None = None,
                     angle_offset: int = 0, signal_store=None) -> RangeAccumulation:
    """Pass 1 over shots [start, stop): labels and histograms.

    ``theta``, ``valid`` : scan angles and validity of the shots from shot
    ``angle_offset`` on (default 0: the WHOLE recording, indexed by shot).
    ``labels_out`` : an h5py dataset (K, H, W) uint8 to write labels into, or None.
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
    K_range = max(0, (stop if stop is not None else start + len(theta) - angle_offset) - start)
    dt = _count_dtype(K_range)
    compiled = K_range * P >= COMPILE_SLOTS  # small recordings need no compiled code
    # the reader checks codes against the file's n_bins: enough when it is ours too;
    # otherwise each chunk is checked below (naming the file), not again in the kernel call
    file_bins = read_system(path).tdc.n_bins
    checked = file_bins <= n_bins
    raw = np.zeros((P, n_bins + 1), dt)
    sig = np.zeros((P, n_bins + 1), dt)
    angle = np.zeros((P, table.n_steps), dt)
    n_per_step = np.zeros(table.n_steps, np.int64)
    conf = np.zeros((3, 3), np.int64)
    has_truth = True
    n_shots = n_unknown = 0
    # the compiled kernel counts raw codes into a uint16 table (half the size of a
    # uint32 one: it stays in the cache more), added to ``raw`` every RAW16_SHOTS
    # shots (no cell can overflow before) instead of once a block; its signal keys go
    # through one buffer reused by every block
    raw16 = np.zeros((P, n_bins + 1), np.uint16) if compiled else None
    in_raw16 = 0
    keys_buf = None
    for s0, _t, bins, truth in iter_shot_chunks(path, settings.chunk_shots, start, stop,
                                                truth_labels=True):
        s1 = s0 + bins.shape[0]
        if raw16 is not None and in_raw16 + (s1 - s0) >= RAW16_SHOTS:
            raw += raw16
            raw16[:] = 0
            in_raw16 = 0
        if compiled and signal_store is not None and (
                keys_buf is None or keys_buf.size < bins.size):
            keys_buf = np.empty(bins.size, np.int64)
        a, b = s0 - angle_offset, s1 - angle_offset
        th, v = theta[a:b], valid[a:b]
        rows = table.rows(th, v)
        if not checked and bins.size and int(bins.max()) > n_bins:
            from mems_stereo.errors import FormatError

            raise FormatError(f"expected codes 0..{n_bins} (tdc.n_bins of the system used), "
                              f"found {int(bins.max())} in shots {s0}..{s1 - 1} (the "
                              f"recording's own system has n_bins = {file_bins})",
                              str(getattr(path, "source", path)), "/shots/bins")
        want = labels_out is not None or truth is not None
        keys = [] if signal_store is not None and compiled else None
        labels, _, _ = classify_and_accumulate(bins, th, v, table, n_bins, raw, sig,
                                               want_labels=want, hist_angle=angle, rows=rows,
                                               compiled=compiled, codes_checked=True,
                                               keys_out=keys,
                                               raw_scratch=(raw16 if s1 - s0 < RAW16_SHOTS
                                                            else None),
                                               keys_scratch=keys_buf)
        if raw16 is not None and s1 - s0 < RAW16_SHOTS:
            in_raw16 += s1 - s0
        if signal_store is not None:
            if keys:
                signal_store.append(keys[0])
            else:
                signal_store.complete = False
        n_per_step += np.bincount(rows[rows >= 0], minlength=table.n_steps)
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
    if raw16 is not None and in_raw16:
        raw += raw16
    return RangeAccumulation(raw, sig, angle, n_per_step, n_shots, n_unknown, conf, has_truth)


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
