"""Pass 2: the detections inside each peak's window, counted per peak, angle step and code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mems_stereo.io.recording import iter_shot_chunks
from mems_stereo.model.system import System
from mems_stereo.pipeline.classify_kernel import COMPILE_SLOTS, compiles
from mems_stereo.pipeline.intervals import IntervalTable
from mems_stereo.pipeline.peak_table import Peaks
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.shot_range import ShotRange
from mems_stereo.util.lazy_numba import compiled_if_loaded, compiled_kernel

# --------------------------------------------------------------------------
# the key of a (peak, angle step, code) triple: written and decoded only here


def _peak_key_py(q, step, code, n_steps, n_codes):
    """Key of (peak q, angle step, code): ``(q · n_steps + step) · n_codes + code``
    (``n_steps`` S of the interval table, ``n_codes`` = n_bins + 1)."""
    return (q * n_steps + step) * n_codes + code


def encode_peak_keys(q, step, code, n_steps: int, n_codes: int) -> np.ndarray:
    """(M,) int64 keys of (peak, step, code) triples (the compiled kernel's layout)."""
    return _peak_key_py(np.asarray(q, np.int64), np.asarray(step, np.int64),
                        np.asarray(code, np.int64), np.int64(n_steps), np.int64(n_codes))


def decode_peak_keys(keys, n_steps: int, n_codes: int):
    """``(q, step, code)``, each (M,) int64, of keys made by :func:`encode_peak_keys`."""
    k = np.asarray(keys, np.int64)
    return k // (n_steps * n_codes), (k // n_codes) % n_steps, k % n_codes


_peak_key = _peak_key_py  # rebound to its compiled form when the kernel is compiled


def _window_keys_py(bins, rows, lo, hi, pix, win_lo, win_hi, step_lo, step_hi, n_steps, nb,
                    out):
    """Reference semantics of the compiled peak-window kernel (see :func:`peak_window_keys`)."""
    K = bins.shape[0]
    Q = pix.shape[0]
    n = 0
    for k in range(K):
        j = rows[k]
        if j < 0:
            continue
        for q in range(Q):
            if j < step_lo[q] or j > step_hi[q]:
                continue
            p = pix[q]
            c = np.int64(bins[k, p])
            if (c != 0 and win_lo[q] <= c and c <= win_hi[q]
                    and np.int64(lo[j, p]) <= c and c <= np.int64(hi[j, p])):
                out[n] = _peak_key(q, j, c, n_steps, nb)
                n += 1
    return n


@dataclass(frozen=True, slots=True)
class PeakWindows:
    """The windows pass 2 counts, one a peak (Q peaks), each (Q,) int64.

    pixel : flat pixel ``row·width + col``; code_lo, code_hi : the codes counted;
    step_lo, step_hi : the scan-angle steps of the interval table counted.
    """

    pixel: np.ndarray
    code_lo: np.ndarray
    code_hi: np.ndarray
    step_lo: np.ndarray
    step_hi: np.ndarray

    @classmethod
    def of_peaks(cls, peaks: Peaks, width: int) -> PeakWindows:
        """The windows of ``peaks`` on a sensor of ``width`` columns."""
        return cls(peaks.pixel(width), *(np.asarray(v, np.int64) for v in (
            peaks.code_lo, peaks.code_hi, peaks.step_lo, peaks.step_hi)))


def _window_keys_numpy(bins, rows, lo, hi, w: PeakWindows, n_steps, nb):
    """The kernel's semantics in vectorised NumPy (small blocks: no compiled code
    to load) over the windows ``w``; returns the keys, (M,) int64, in the same (shot,
    peak) order."""
    pix, win_lo, win_hi, step_lo, step_hi = w.pixel, w.code_lo, w.code_hi, w.step_lo, w.step_hi
    c = bins[:, pix].astype(np.int64)  # (K, Q)
    j = rows[:, None]
    jc = np.maximum(rows, 0)
    m = ((j >= 0) & (j >= step_lo) & (j <= step_hi) & (c != 0) & (win_lo <= c) & (c <= win_hi)
         & (lo[jc][:, pix] <= c) & (c <= hi[jc][:, pix]))
    kk, qq = np.nonzero(m)
    return encode_peak_keys(qq, rows[kk], c[kk, qq], n_steps, nb)


def _compiled_window_keys():
    """The numba kernel, compiled (or loaded from numba's disk cache) on first use, its
    key helper ``_peak_key`` inlined (:func:`~mems_stereo.util.lazy_numba.compiled_kernel`);
    None when numba is absent."""
    return compiled_kernel(_window_keys_py, helpers={"_peak_key": _peak_key_py})


def peak_window_keys(bins, theta, valid, table: IntervalTable, windows: PeakWindows,
                     n_bins: int, compiled: bool | None = None) -> np.ndarray:
    """Keys of the signal detections inside the peak windows of a block of shots.

    A detection of pixel ``windows.pixel[q]`` counts when its code lies in the
    peak's window ``[code_lo[q], code_hi[q]]``, its shot's angle step in
    ``[step_lo[q], step_hi[q]]`` (None: any) and the classifier accepted it
    (signal).  Its key is :func:`encode_peak_keys` of ``(q, step, code)``, with
    ``step`` the shot's angle step in ``table`` (S steps, n_bins + 1 codes).  Returns (M,) int64,
    in shot order.  One compiled pass over the peak pixels only (``compiled``
    None: for blocks of at least ``COMPILE_SLOTS`` pixel-slots, else the same
    in NumPy; True/False force either).
    """
    b = np.ascontiguousarray(bins)
    K = b.shape[0]
    b2 = b.reshape(K, -1)
    if b2.dtype != np.uint16:
        b2 = b2.astype(np.uint16)
    rows = table.rows(theta, valid)
    table.ensure(rows)
    pix = np.asarray(windows.pixel, dtype=np.int64)
    s_lo = (np.zeros(pix.size, np.int64) if windows.step_lo is None
            else np.asarray(windows.step_lo, np.int64))
    s_hi = (np.full(pix.size, table.n_steps, np.int64) if windows.step_hi is None
            else np.asarray(windows.step_hi, np.int64))
    w = PeakWindows(pix, np.asarray(windows.code_lo, np.int64),
                    np.asarray(windows.code_hi, np.int64), s_lo, s_hi)
    if compiled is None:
        compiled = b2.size >= COMPILE_SLOTS
    kernel = _compiled_window_keys() if compiled else None
    if kernel is None:
        return _window_keys_numpy(b2, rows, table.lo, table.hi, w, int(table.n_steps),
                                  int(n_bins) + 1)
    out = np.empty(K * max(1, pix.size), np.int64)
    n = kernel(b2, rows, table.lo, table.hi, w.pixel, w.code_lo, w.code_hi, w.step_lo,
               w.step_hi, int(table.n_steps), int(n_bins) + 1, out)
    return out[:n].copy()


def merge_sorted_counts(keys, counts, new_keys, new_counts):
    """Add ``new_counts`` at ``new_keys`` to ``counts`` at ``keys`` (both key arrays
    sorted and unique, int64): returns the merged ``(keys, counts)``, sorted unique.

    Integer arithmetic in place where a key exists (``counts`` is updated), one
    insertion of the new keys otherwise: the temporaries are O(len(new_keys))
    plus the merged arrays.
    """
    keys = np.asarray(keys, np.int64)
    counts = np.asarray(counts, np.int64)
    new_keys = np.asarray(new_keys, np.int64)
    new_counts = np.asarray(new_counts, np.int64)
    if keys.size == 0:
        return new_keys.copy(), new_counts.copy()
    if new_keys.size == 0:
        return keys, counts
    pos = np.searchsorted(keys, new_keys)
    hit = keys[np.minimum(pos, keys.size - 1)] == new_keys
    hit &= pos < keys.size
    counts[pos[hit]] += new_counts[hit]
    if hit.all():
        return keys, counts
    miss = ~hit
    return (np.insert(keys, pos[miss], new_keys[miss]),
            np.insert(counts, pos[miss], new_counts[miss]))


def _merge_two_py(ka, ca, kb, cb, keys, counts) -> int:
    """Merge two sorted unique key sets with their counts into ``keys, counts`` (room
    for at least the merged keys): returns the number of merged keys (the keys sorted
    unique, the counts of a key in both added) — :func:`merge_sorted_counts`' result
    in one linear pass."""
    i = j = m = 0
    na, nb = ka.shape[0], kb.shape[0]
    while i < na and j < nb:
        a, b = ka[i], kb[j]
        if a < b:
            keys[m], counts[m] = a, ca[i]
            i += 1
        elif b < a:
            keys[m], counts[m] = b, cb[j]
            j += 1
        else:
            keys[m], counts[m] = a, ca[i] + cb[j]
            i += 1
            j += 1
        m += 1
    while i < na:
        keys[m], counts[m] = ka[i], ca[i]
        i += 1
        m += 1
    while j < nb:
        keys[m], counts[m] = kb[j], cb[j]
        j += 1
        m += 1
    return m


#: both key sets at least this large: :func:`_merged` merges them in one compiled pass
#: where numba is loaded already (a dense run's pass 1 loaded it)
MERGE_COMPILED_KEYS = 1 << 14


def _merged(keys, counts, new_keys, new_counts):
    """:func:`merge_sorted_counts` (``counts`` may be updated in place), in one compiled
    linear pass (:func:`_merge_two_py`, the same arrays) where both sets hold at least
    :data:`MERGE_COMPILED_KEYS` keys and numba is loaded already (the searches and
    insertions of :func:`merge_sorted_counts` are a large part of pass 2 on a dense
    recording)."""
    kernel = (compiled_if_loaded(_merge_two_py)
              if min(keys.size, new_keys.size) >= MERGE_COMPILED_KEYS else None)
    if kernel is None:
        return merge_sorted_counts(keys, counts, new_keys, new_counts)
    keys, new_keys = np.asarray(keys, np.int64), np.asarray(new_keys, np.int64)
    # the merged size first (a pass without writes), so the output is allocated once
    n = keys.size + new_keys.size - compiled_if_loaded(_common_keys_py)(keys, new_keys)
    out_k, out_c = np.empty(n, np.int64), np.empty(n, np.int64)
    kernel(keys, np.asarray(counts, np.int64), new_keys, np.asarray(new_counts, np.int64),
           out_k, out_c)
    return out_k, out_c


def _common_keys_py(ka, kb) -> int:
    """How many keys two sorted unique key sets share (one linear pass)."""
    i = j = n = 0
    while i < ka.shape[0] and j < kb.shape[0]:
        if ka[i] < kb[j]:
            i += 1
        elif kb[j] < ka[i]:
            j += 1
        else:
            n += 1
            i += 1
            j += 1
    return n


class PeakCounts:
    """How often each distinct (peak, scan-angle step, code) occurs among the signal
    detections inside the peak windows: integers, so sums over chunks and workers
    are exact in any order.

    Keys are :func:`encode_peak_keys` of (peak, step, code) with S the interval
    table's number of angle steps (:func:`decode_peak_keys` reads them back);
    ``keys`` (U,) int64 sorted unique,
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
                self.merge_pending()

    def merge_pending(self) -> None:
        """Merge the buffered keys into ``keys``, ``counts``."""
        if not self._pending:
            return
        new = np.concatenate(self._pending)
        self._pending, self._n_pending = [], 0
        k, c = np.unique(new, return_counts=True)
        del new
        self.keys, self.counts = _merged(self.keys, self.counts, k,
                                         c.astype(np.int64, copy=False))

    def __add__(self, other: PeakCounts) -> PeakCounts:
        self.merge_pending()
        other.merge_pending()
        return PeakCounts(*_merged(self.keys, self.counts.copy(), other.keys, other.counts))

    def finished(self) -> PeakCounts:
        """These counts with every buffered key merged."""
        self.merge_pending()
        return self


def peak_counts_range(path, system: System, shots: ShotRange, settings: Settings,
                      peaks: Peaks, progress=None,
                      table: IntervalTable | None = None) -> PeakCounts:
    """Pass 2 over the shots of ``shots``: count the peak windows' signal detections by
    (peak, angle step, code) — see :class:`PeakCounts` and
    :func:`mems_stereo.pipeline.pass2.peak_window_keys`.  ``table`` : the run's
    interval table (default: a new one); ``progress(n)`` : called after each chunk of
    n shots."""
    if table is None:
        table = IntervalTable.for_settings(system, settings)
    W = system.receiver.width
    windows = PeakWindows.of_peaks(peaks, W)
    pc = PeakCounts()
    if windows.pixel.size == 0:
        return pc
    compiled = compiles(shots.n_shots * system.receiver.width * system.receiver.height,
                        COMPILE_SLOTS)
    for s0, _t, bins in iter_shot_chunks(path, settings.chunk_shots, shots.start, shots.stop):
        s1 = s0 + bins.shape[0]
        theta, valid = shots.angles(s0, s1)
        pc.add_keys(peak_window_keys(bins, theta, valid, table, windows, system.tdc.n_bins,
                                     compiled=compiled))
        if progress is not None:
            progress(s1 - s0)
    return pc.finished()


# --------------------------------------------------------------------------
# one pass for the matched filter's candidates and the first stage's peaks


def _select_py(keys_in, counts_in, to, lo, hi, span, n_codes, n_steps, keys, counts) -> int:
    """:func:`select_counts`' selection in one pass: the keys of peaks with ``to`` ≥ 0
    and steps within ``lo..hi`` renumbered, in input order, written to ``keys,
    counts``; returns their number."""
    m = 0
    for i in range(keys_in.shape[0]):
        k = keys_in[i]
        q = k // span
        t = to[q]
        if t < 0:
            continue
        step = (k // n_codes) % n_steps
        if step < lo[q] or step > hi[q]:
            continue
        keys[m] = t * span + k % span
        counts[m] = counts_in[i]
        m += 1
    return m


@dataclass(frozen=True, slots=True)
class CountSelection:
    """Which peaks of a :class:`PeakCounts` to keep, renumbered, over which steps
    (:func:`select_counts`), each (M,) int64.

    src : the peaks kept (distinct); dst : their numbers in the result; step_lo,
    step_hi : the steps of each kept over which its counts are kept.
    """

    src: np.ndarray
    dst: np.ndarray
    step_lo: np.ndarray
    step_hi: np.ndarray


def select_counts(pc: PeakCounts, sel: CountSelection, n_steps: int,
                  n_codes: int) -> PeakCounts:
    """The counts of peaks ``sel.src`` of ``pc`` renumbered ``sel.dst``, each over its
    steps ``sel.step_lo..sel.step_hi`` only, keys sorted: the :class:`PeakCounts` of
    counting those peaks over those windows (each key's count is the same whichever
    other windows were counted with it)."""
    src, dst, step_lo, step_hi = sel.src, sel.dst, sel.step_lo, sel.step_hi
    span = np.int64(n_steps) * np.int64(n_codes)
    src = np.asarray(src, np.int64)
    if pc.keys.size == 0 or src.size == 0:
        return PeakCounts()
    n = int(max(pc.keys[-1] // span, src.max())) + 1  # (keys sorted: the last's peak)
    to = np.full(n, -1, np.int64)
    lo = np.zeros(n, np.int64)
    hi = np.full(n, -1, np.int64)
    to[src] = dst
    lo[src] = step_lo
    hi[src] = step_hi
    kernel = (compiled_if_loaded(_select_py) if pc.keys.size >= MERGE_COMPILED_KEYS
              else None)
    if kernel is not None:  # the same selection in one compiled pass
        keys, counts = np.empty(pc.keys.size, np.int64), np.empty(pc.keys.size, np.int64)
        m = kernel(pc.keys, pc.counts, to, lo, hi, span, np.int64(n_codes),
                   np.int64(n_steps), keys, counts)
        keys, counts = keys[:m].copy(), counts[:m].copy()
        if m < 2 or bool(np.all(keys[1:] > keys[:-1])):
            return PeakCounts(keys, counts)
        order = np.argsort(keys, kind="stable")
        return PeakCounts(keys[order], counts[order])
    q = pc.keys // span
    step = (pc.keys // np.int64(n_codes)) % np.int64(n_steps)
    m = (to[q] >= 0) & (step >= lo[q]) & (step <= hi[q])
    keys = to[q[m]] * span + pc.keys[m] % span
    if keys.size < 2 or bool(np.all(keys[1:] > keys[:-1])):
        # renumbered in the same order (e.g. the candidates, which follow the first
        # stage's peaks): sorted already, no sort (the same arrays)
        return PeakCounts(keys, pc.counts[m])
    order = np.argsort(keys, kind="stable")
    return PeakCounts(keys[order], pc.counts[m][order])


def with_widened_candidates(first: Peaks, cands, n_steps: int) -> Peaks:
    """The windows to count in one pass for the matched filter and the peaks: the first
    stage's peaks (Qa) followed by the candidates (C) over their steps widened by 1.5
    footprints each side (``cands.width``): any peak a candidate can confirm counts
    inside (:func:`~mems_stereo.pipeline.matched.confirm` centres it within the
    candidate's steps and counts ± 1.5 footprints around it).  Qa + C light peaks."""
    H = cands.width + cands.width // 2
    ext = cands.light().arrays()
    ext["step_lo"] = np.maximum(0, np.asarray(cands.step_lo, np.int64) - H)
    ext["step_hi"] = np.minimum(n_steps - 1, np.asarray(cands.step_hi, np.int64) + H)
    return Peaks(**{k: np.concatenate([v, ext[k]]) for k, v in first.arrays().items()})


def candidate_selection(n_first: int, cands) -> CountSelection:
    """The :class:`CountSelection` of the candidates' own counts from a count of
    :func:`with_widened_candidates`."""
    C = len(cands)
    return CountSelection(n_first + np.arange(C), np.arange(C), cands.step_lo,
                          cands.step_hi)


def merged_selection(first, cands, peaks, width: int) -> CountSelection:
    """The :class:`CountSelection` for ``peaks`` (the first stage's ``first`` and the
    candidates it confirmed, merged in pixel order) from a count of
    :func:`with_widened_candidates`: the first stage's counts renumbered, each
    confirmed peak's over its own window.  ``width`` : the sensor's columns."""
    pix, fp = peaks.pixel(width), first.pixel(width)
    cp = cands.pixel(width)
    new = np.flatnonzero(~np.isin(pix, fp))
    Qa = fp.size
    return CountSelection(
        np.concatenate([np.arange(Qa), Qa + np.searchsorted(cp, pix[new])]),
        np.concatenate([np.searchsorted(pix, fp), new]),
        np.concatenate([np.zeros(Qa, np.int64), np.asarray(peaks.step_lo)[new]]),
        np.concatenate([np.full(Qa, np.iinfo(np.int64).max),
                        np.asarray(peaks.step_hi)[new]]))
