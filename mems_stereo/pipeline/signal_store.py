"""Pass 1's signal detections kept for pass 2, so that one process reads the shots once.

Pass 2 counts the signal detections inside the peaks' windows
(:mod:`mems_stereo.pipeline.pass2`); every one of them is a detection pass 1
labelled signal.  :class:`SignalStore` keeps each signal detection's key
``pixel << shift_p | angle step << shift_j | code`` (int64 bit fields,
:func:`~mems_stereo.pipeline.classify_kernel.signal_key_shifts`; 8 bytes; about
8 % of a dense floodlight recording's pixel-slots) in memory up to
``memory_bytes`` and in an anonymous temporary file beyond, and
:func:`peak_counts_from_store` counts the windows' keys from it: the same
:class:`~mems_stereo.pipeline.pass2.PeakCounts` as reading the shots again,
without decompressing them a second time.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from mems_stereo.errors import OptionError
from mems_stereo.model.system import System
from mems_stereo.pipeline.classify_kernel import decode_signal_keys, signal_key_shifts
from mems_stereo.pipeline.pass2 import PeakCounts, encode_peak_keys
from mems_stereo.pipeline.peak_table import Peaks
from mems_stereo.util.lazy_numba import compiled_kernel

#: signal keys held in memory before the store spills to a temporary file (bytes)
STORE_MEMORY_BYTES = 8 << 20
#: keys read back from the file at a time
READ_KEYS = 1 << 18


def rereading_decompresses(source) -> bool:
    """Whether reading ``source``'s shots again costs a decompression (its
    ``/shots/bins`` is stored with a filter such as gzip): only then does keeping
    the signal detections save work.  An uncompressed file is read again from
    the page cache faster than its signal keys are written and read back
    (8 bytes a signal detection against 2 bytes a pixel-slot, for the 8 % of
    slots of a dense recording); a :class:`~mems_stereo.io.recording.Recording`
    in memory needs no reading at all."""
    if not isinstance(source, (str, os.PathLike)):
        return False
    from mems_stereo.io import hdf5 as h5

    with h5.open_h5(source) as f:
        ds = h5.dataset(f, "/shots/bins", str(source))
        return ds.id.get_create_plist().get_nfilters() > 0


class SignalStore:
    """Signal-detection keys of one run, appended chunk by chunk (see module doc).

    ``complete`` is False once a chunk was classified without keys (pass 2
    must then read the shots).  ``directory`` : where the temporary file goes
    (default: the system's temporary directory).
    """

    def __init__(self, memory_bytes: int = STORE_MEMORY_BYTES, directory=None):
        self.memory_bytes = int(memory_bytes)
        self.directory = directory
        self.complete = True
        self.n_keys = 0
        self._held: list[np.ndarray] = []
        self._held_bytes = 0
        self._file = None

    def append(self, keys) -> None:
        k = np.ascontiguousarray(keys, dtype=np.int64)
        self.n_keys += k.size
        if self._file is None and self._held_bytes + k.nbytes <= self.memory_bytes:
            self._held.append(k)
            self._held_bytes += k.nbytes
            return
        if self._file is None:
            self._file = tempfile.TemporaryFile(dir=self.directory)
            for h in self._held:
                h.tofile(self._file)
            self._held, self._held_bytes = [], 0
        k.tofile(self._file)

    def blocks(self):
        """The keys in the order appended, as int64 arrays of at most :data:`READ_KEYS`
        (from the file) or as appended (in memory)."""
        if self._file is None:
            yield from self._held
            return
        self._file.flush()
        self._file.seek(0)
        left = self.n_keys
        while left > 0:
            k = np.fromfile(self._file, np.int64, min(READ_KEYS, left))
            if k.size == 0:  # pragma: no cover - a truncated file
                raise OSError("signal store: temporary file shorter than written")
            left -= k.size
            yield k

    def __sizeof__(self) -> int:  # what Dask sees: the keys (it keeps a task near them)
        return object.__sizeof__(self) + 8 * self.n_keys

    def __getstate__(self):  # between processes (Dask): the keys themselves
        d = dict(self.__dict__)
        d["_held"] = [np.concatenate(list(self.blocks()))] if self.n_keys else []
        d["_held_bytes"] = 8 * self.n_keys
        d["_file"] = None
        return d

    def __setstate__(self, d):
        self.__dict__.update(d)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self._held = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def window_keys_from_signal(keys, n_steps: int, nb: int, first, order, win_lo, win_hi,
                            step_lo, step_hi) -> np.ndarray:
    """Pass-2 keys (:func:`~mems_stereo.pipeline.pass2.encode_peak_keys` of (peak, step,
    code)) of the signal keys ``keys``
    (:func:`~mems_stereo.pipeline.classify_kernel.encode_signal_keys`) that fall in a
    peak's code and step windows.

    ``first`` (P + 1,) and ``order`` (Q,): the peaks of pixel p are
    ``order[first[p]:first[p + 1]]``; ``win_lo``, ``win_hi``, ``step_lo``,
    ``step_hi`` (Q,) int64.  Vectorised over the keys, one pass per rank of a
    pixel's peaks (a pixel holds one or a few)."""
    p, j, c = decode_signal_keys(keys, n_steps, nb)
    n_of = first[1:] - first[:-1]
    out = []
    for r in range(int(n_of.max()) if n_of.size else 0):
        has = n_of[p] > r
        idx = np.flatnonzero(has)
        q = order[first[p[idx]] + r]
        jj, cc = j[idx], c[idx]
        m = (jj >= step_lo[q]) & (jj <= step_hi[q]) & (cc >= win_lo[q]) & (cc <= win_hi[q])
        out.append(encode_peak_keys(q[m], jj[m], cc[m], n_steps, nb))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def _window_keys_py(keys, shift_j, shift_p, n_steps, nb, first, order, win_lo, win_hi,
                    step_lo, step_hi, out):
    """Reference semantics of the compiled form of :func:`window_keys_from_signal`: the
    same keys, key by key (for each key, its pixel's peaks in rank order), written
    to ``out`` (room for ``keys.size`` times the most peaks of a pixel); returns
    how many.  ``shift_j``, ``shift_p`` : the keys' bit fields
    (:func:`~mems_stereo.pipeline.classify_kernel.signal_key_shifts`)."""
    mask_j = (np.int64(1) << (shift_p - shift_j)) - 1
    mask_c = (np.int64(1) << shift_j) - 1
    n = 0
    for i in range(keys.shape[0]):
        k = keys[i]
        p = k >> shift_p
        a = first[p]
        b = first[p + 1]
        if a == b:
            continue
        j = (k >> shift_j) & mask_j
        c = k & mask_c
        for t in range(a, b):
            q = order[t]
            if step_lo[q] <= j and j <= step_hi[q] and win_lo[q] <= c and c <= win_hi[q]:
                out[n] = (q * n_steps + j) * nb + c
                n += 1
    return n


def _compiled_window_keys():
    """The numba form of :func:`_window_keys_py` (numba's disk cache), None without numba.
    Only runs that hold a store use it, and those loaded pass 1's compiled kernels."""
    return compiled_kernel(_window_keys_py)


def window_keys_compiled(keys, n_steps: int, nb: int, first, order, win_lo, win_hi,
                         step_lo, step_hi, kernel=None) -> np.ndarray:
    """:func:`window_keys_from_signal` in one compiled pass over the keys (the same
    keys, in key order instead of rank order: PeakCounts sums them whatever the
    order); ``kernel`` : the function to run (default: the compiled one)."""
    k = np.ascontiguousarray(keys, np.int64)
    n_of = first[1:] - first[:-1]
    rank = int(n_of.max()) if n_of.size else 0
    if k.size == 0 or rank == 0:
        return np.zeros(0, np.int64)
    out = np.empty(k.size * rank, np.int64)
    run = kernel if kernel is not None else _compiled_window_keys()
    shift_j, shift_p = signal_key_shifts(n_steps, nb)
    n = run(k, np.int64(shift_j), np.int64(shift_p), np.int64(n_steps), np.int64(nb), first,
            order, win_lo, win_hi, step_lo, step_hi, out)
    return out[:n].copy()


def peak_counts_from_store(store: SignalStore, system: System, peaks: Peaks,
                           n_steps: int) -> PeakCounts:
    """Pass 2 from the stored signal keys: the same :class:`PeakCounts` as
    :func:`~mems_stereo.pipeline.pass2.peak_counts_range` over the shots that filled
    ``store`` (exact integer counts: the order of the keys does not matter)."""
    if not store.complete:
        raise OptionError("signal store is incomplete: pass 2 must read the shots",
                          field="store")
    W, H = system.receiver.width, system.receiver.height
    pix = peaks.pixel(W)
    pc = PeakCounts()
    if pix.size == 0:
        return pc
    nb = system.tdc.n_bins + 1
    order = np.argsort(pix, kind="stable")
    first = np.searchsorted(pix[order], np.arange(W * H + 1))
    s_lo = (np.zeros(pix.size, np.int64) if peaks.step_lo is None
            else np.asarray(peaks.step_lo, np.int64))
    s_hi = (np.full(pix.size, n_steps, np.int64) if peaks.step_hi is None
            else np.asarray(peaks.step_hi, np.int64))
    lo = np.asarray(peaks.code_lo, np.int64)
    hi = np.asarray(peaks.code_hi, np.int64)
    first = first.astype(np.int64)
    order = order.astype(np.int64)
    # compiled where numba is at hand (a store is filled by pass 1's compiled kernel, so
    # numba is loaded already): several times the vectorised form's speed
    fn = (window_keys_compiled if _compiled_window_keys() is not None
          else window_keys_from_signal)
    for k in store.blocks():
        pc.add_keys(fn(k, n_steps, nb, first, order, lo, hi, s_lo, s_hi))
    return pc.finished()
