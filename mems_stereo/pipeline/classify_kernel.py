"""Pass 1's kernel: label a block of shots and add it to its pixels' histograms.

The compiled kernel looks each shot's accepted code interval up in the
:class:`~mems_stereo.pipeline.intervals.IntervalTable`; the pure-Python
kernels beside it are its reference semantics; small blocks use the same
semantics in vectorised NumPy, so that they never load compiled code.  The
signal detections' keys (:func:`encode_signal_keys`) let pass 2 count from
them instead of reading the shots again.
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
from dataclasses import dataclass

import numpy as np

from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.util.lazy_numba import compiled_kernel

#: blocks of fewer shots than this count their raw histogram in uint16 first
#: (:func:`classify_and_accumulate`)
RAW16_SHOTS = 1 << 16




@dataclass
class Pass1Histograms:
    """Pass 1's counts of the P pixels of a block of shots, added to in place.

    raw, signal : (P, n_bins + 1) integer (uint32 in the pipeline), column N counts
    code N (column 0 of ``raw``: valid pixel-slots without a detection); the noise
    histogram is ``raw − signal`` (columns 1..n_bins).  angle : (P, S) integer,
    signal detections per pixel and angle step of the interval table.
    """

    raw: np.ndarray
    signal: np.ndarray
    angle: np.ndarray

    @classmethod
    def zeros(cls, n_pixels: int, n_bins: int, n_steps: int, dtype=np.uint32) -> Pass1Histograms:
        """Empty histograms of ``dtype``."""
        return cls(np.zeros((n_pixels, n_bins + 1), dtype), np.zeros((n_pixels, n_bins + 1), dtype),
                   np.zeros((n_pixels, n_steps), dtype))


@dataclass(frozen=True, slots=True)
class KernelOptions:
    """How :func:`classify_and_accumulate` runs, and the buffers it reuses.

    compiled : True: the numba kernel; False: the same in NumPy; None (default):
        numba for blocks of at least :data:`COMPILE_SLOTS` pixel-slots.
    codes_checked : the caller has checked every code <= n_bins already
        (:func:`~mems_stereo.io.recording.iter_shot_chunks` does).
    keys_out : a list to append the block's signal keys to (:func:`signal_keys`:
        (pixel, angle step, code), int64), for pass 2 to count from instead of
        reading the shots again; only on the compiled path (the list is left
        untouched otherwise, and the caller reads the shots).
    raw_scratch : a (H*W, n_bins + 1) uint16 table that the compiled kernel counts
        the raw codes into instead of ``raw`` (left untouched); the caller adds
        it to ``raw`` before it could hold 2**16 shots
        (:func:`~mems_stereo.pipeline.pass1.accumulate_range` does, every
        :data:`RAW16_SHOTS` shots).  Ignored on the NumPy path.
    keys_scratch : an int64 buffer of at least K*H*W that the compiled kernel writes
        the signal keys into before they are copied to ``keys_out`` (reused between
        blocks: no fresh buffer per block).
    """

    compiled: bool | None = None
    codes_checked: bool = False
    keys_out: list | None = None
    raw_scratch: np.ndarray | None = None
    keys_scratch: np.ndarray | None = None


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
    division)."""
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
#: within :func:`compiled_blocks`: blocks of any size run the compiled kernels
_ANY_SIZE = contextvars.ContextVar("compiled_any_size", default=False)


@contextlib.contextmanager
def compiled_blocks():
    """Context in which :func:`compiles` is true for blocks of any size where numba is
    imported already: the frames of a live run, whose processor loads the kernels once
    and whose few thousand shots a frame then cost one compiled pass instead of NumPy's
    (K, P) temporaries.  The compiled and NumPy forms count the same integers."""
    token = _ANY_SIZE.set("numba" in sys.modules)
    try:
        yield
    finally:
        _ANY_SIZE.reset(token)


def compiles(slots: int, threshold: int = COMPILE_SLOTS) -> bool:
    """Whether a block of ``slots`` pixel-slots runs the compiled kernels: from
    ``threshold`` on, or any block inside :func:`compiled_blocks`."""
    return slots >= threshold or _ANY_SIZE.get()

def _compiled():
    """The numba kernels ``(labels, no labels, signal keys)``, compiled (or loaded from
    numba's disk cache) on first use (:func:`~mems_stereo.util.lazy_numba.compiled_kernel`);
    None when numba is absent."""
    kernels = tuple(compiled_kernel(k) for k in (_kernel_py, _kernel_nolabels_py,
                                                 _kernel_keys_py))
    return None if kernels[0] is None else kernels


def classify_and_accumulate(bins, theta, valid, table: IntervalTable, n_bins: int,
                            hists: Pass1Histograms | None = None, want_labels: bool = True,
                            rows=None, options: KernelOptions | None = None):
    """Label a block of shots and add it to the raw and signal histograms.

    Parameters
    ----------
    bins : (K, H, W) uint16 TDC codes.
    theta : (K,) rad; valid : (K,) bool (False: shot left out, label 0,
        not counted).
    table : :class:`IntervalTable` of the system (rows filled on demand).
    n_bins : codes above it raise :class:`~mems_stereo.errors.FormatError`.
    hists : :class:`Pass1Histograms` of the H*W pixels, added to in place (uint32
        allocated when None).
    want_labels : return the (K, H, W) uint8 labels (else None).
    rows : (K,) int64 table rows of the shots (:meth:`IntervalTable.rows`),
        when the caller has them already.
    options : :class:`KernelOptions` (default: the kernel chosen by the block's size,
        codes checked here, no keys).

    Returns
    -------
    ``(labels, hists)``.
    """
    opt = KernelOptions() if options is None else options
    b = np.ascontiguousarray(bins)
    if b.dtype != np.uint16:
        b = b.astype(np.uint16)
    K = b.shape[0]
    P = int(np.prod(b.shape[1:]))
    b2 = b.reshape(K, P)
    if not opt.codes_checked and b2.size and int(b2.max()) > n_bins:  # kernel: no bounds checks
        from mems_stereo.errors import FormatError

        raise FormatError(f"expected codes 0..{n_bins}, found {int(b2.max())}", field="bins")
    if rows is None:
        rows = table.rows(theta, valid)
    table.ensure(rows)
    if hists is None:
        hists = Pass1Histograms.zeros(P, n_bins, table.n_steps)
    hist_raw, hist_signal, hist_angle = hists.raw, hists.signal, hists.angle
    labels = np.empty((K, P), dtype=np.uint8) if want_labels else None
    compiled = b2.size >= COMPILE_SLOTS if opt.compiled is None else opt.compiled
    kernels = _compiled() if compiled else None
    if kernels is None:
        _kernel_numpy(b2, rows, table.lo, table.hi, labels, hist_raw, hist_signal, hist_angle)
        return (labels.reshape(b.shape) if want_labels else None), hists
    # the compiled kernels count every slot into the raw histogram at a random code:
    # a block of fewer than 2**16 shots counts into a uint16 table of half the size
    # (it stays in the cache more), added to hist_raw after (exact: no cell can count
    # more than the block's shots)
    if opt.raw_scratch is not None:
        raw = opt.raw_scratch
    else:
        raw = np.zeros(hist_raw.shape, np.uint16) if K < RAW16_SHOTS else hist_raw
    keys_out = opt.keys_out
    if want_labels:
        kernels[0](b2, rows, table.lo, table.hi, labels, raw, hist_signal, hist_angle)
        if keys_out is not None:
            keys_out.append(signal_keys(b2, rows, labels, table.n_steps, n_bins + 1))
    elif keys_out is not None:
        ks = opt.keys_scratch
        buf = ks if ks is not None and ks.size >= b2.size else np.empty(b2.size, np.int64)
        n = kernels[2](b2, rows, table.lo, table.hi, raw, hist_signal, hist_angle,
                       *signal_key_shifts(table.n_steps, n_bins + 1), buf)
        keys_out.append(buf[:n].copy())
    else:
        kernels[1](b2, rows, table.lo, table.hi, raw, hist_signal, hist_angle)
    if raw is not hist_raw and raw is not opt.raw_scratch:
        hist_raw += raw
    return (labels.reshape(b.shape) if want_labels else None), hists
