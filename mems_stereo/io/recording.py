"""HDF5 recordings of FORMAT v1: read, validate, write, and read in chunks of shots.

A recording holds one frame or run: the system description as known when
recording (``/system``), the shot trigger times and TDC codes
(``/shots/time``, ``/shots/bins``), the zero crossings of θ_mech
(``/scanner/zero_crossings``, ``/scanner/rising``), and for simulated data a
``/truth`` group that processing never reads.

Errors are :class:`~mems_stereo.errors.FormatError` naming the file, the
dataset and what was wrong (the checks: :mod:`mems_stereo.io.recording_checks`).
Writers are atomic (:func:`mems_stereo.util.atomic.atomic_output`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.deflate_chunks import chunk_reader
from mems_stereo.io.recording_checks import (
    FORMAT_NAME,
    FORMAT_VERSION,
    RecordingHeader,
    check_label_values,
    check_truth,
    read_truth,
    validate_header,
    validate_recording_file,
)
from mems_stereo.model.scanner import validate_zero_crossings
from mems_stereo.model.system import System, system_to_json
from mems_stereo.util.atomic import atomic_output
from mems_stereo.util.limits import check_allocation

TRUTH_DATASETS = ("label", "theta", "point")


@dataclass
class Recording:
    """A recording in memory (or with ``bins`` as a lazy h5py dataset).

    Attributes
    ----------
    system : System as recorded (nominal).
    shot_time : (K,) float64, s.
    bins : (K, H, W) uint16 TDC codes, 0 = no detection.
    zero_crossings : (Z,) float64, s, increasing.
    rising : (Z,) uint8.
    truth : dict of optional arrays (``label`` (K,H,W) uint8, ``theta`` (K,)
        rad, ``point`` (K,3) m) and anything else under /truth.
    source : file name for messages.

    Examples
    --------
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> rec.bins.shape, rec.bins.dtype, rec.shot_time.shape, rec.zero_crossings.shape
    ((800, 1, 192), dtype('uint16'), (800,), (129,))
    >>> sorted(rec.truth)[:3]
    ['label', 'object', 'path_length']
    """

    system: System
    shot_time: np.ndarray
    bins: np.ndarray
    zero_crossings: np.ndarray
    rising: np.ndarray
    truth: dict = field(default_factory=dict)
    source: str = "<memory>"

    @property
    def n_shots(self) -> int:
        return int(self.shot_time.shape[0])

    @property
    def has_truth(self) -> bool:
        return "label" in self.truth

    def __repr__(self) -> str:
        K = self.n_shots
        dur = float(self.shot_time[-1] - self.shot_time[0]) if K > 1 else 0.0
        return (f"<Recording {self.source}: {K} shots x {tuple(self.bins.shape[1:])} pixels, "
                f"{dur * 1e3:.3g} ms, {len(self.zero_crossings)} zero crossings"
                f"{', with truth' if self.has_truth else ''}>")

    @classmethod
    def concatenate(cls, chunks) -> Recording:
        """One recording from consecutive chunks of shots of one acquisition.

        ``chunks`` : Recordings of the same system, shot times increasing
        across chunks.  Zero crossings are merged (duplicates, as two chunks
        that both carry the same crossing, kept once); truth arrays with one
        entry per shot are joined.
        """
        chunks = list(chunks)
        if not chunks:
            raise FormatError("expected at least one chunk of shots", field="chunks")
        first = chunks[0]
        if len(chunks) == 1:
            return first
        ref = system_to_json(first.system)
        for c in chunks[1:]:
            if c.system is not first.system and system_to_json(c.system) != ref:
                raise FormatError("expected chunks of one system, found different ones",
                                  c.source, "/system")
        t = np.concatenate([np.asarray(c.shot_time, np.float64) for c in chunks])
        if np.any(np.diff(t) <= 0):
            raise FormatError("expected chunks in shot order (strictly increasing times)",
                              field="/shots/time")
        zc = np.concatenate([np.asarray(c.zero_crossings, np.float64) for c in chunks])
        ri = np.concatenate([np.asarray(c.rising, np.uint8) for c in chunks])
        zc, keep = np.unique(zc, return_index=True)
        zc, ri = validate_zero_crossings(zc, ri[keep], source=first.source)
        truth = {}
        for k in first.truth:
            parts = [c.truth.get(k) for c in chunks]
            if all(p is not None and np.ndim(p) and len(p) == c.n_shots
                   for p, c in zip(parts, chunks)):
                truth[k] = np.concatenate(parts)
        bins = np.concatenate([np.asarray(c.bins) for c in chunks])
        return cls(first.system, t, bins, zc, ri.astype(np.uint8), truth,
                   f"{first.source} (+{len(chunks) - 1} chunks)")


def read_recording(path: str | os.PathLike, *, truth: bool = True) -> Recording:
    """Read and validate a whole recording into memory.

    For recordings larger than memory use :func:`iter_shot_chunks`.

    Examples
    --------
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> rec.bins.shape, int((rec.bins > 0).sum())          # shots x rows x columns, detections
    ((800, 1, 192), 19518)
    >>> rec.system.tdc.n_bins
    4096
    """
    source = str(path)
    with h5.open_h5(path) as f:
        hdr = validate_recording_file(f, source, check_codes=False)
        system, t, zc, rising = hdr.system, hdr.shot_time, hdr.zero_crossings, hdr.rising
        bins = h5.read(h5.dataset(f, "/shots/bins", source, whole=True), source)
        if bins.size and int(bins.max()) > system.tdc.n_bins:
            k = int(np.argmax(bins.reshape(bins.shape[0], -1).max(axis=1) > system.tdc.n_bins))
            raise FormatError(f"expected codes 0..{system.tdc.n_bins} (n_bins), found "
                              f"{int(bins.max())} in shot {k}", source, "/shots/bins")
        tr = read_truth(f, source) if truth else {}
    return Recording(system, t, bins, zc, rising, tr, source)


def read_header(path: str | os.PathLike | Recording,
                check_codes: bool = False) -> RecordingHeader:
    """Validate a recording and read all but ``/shots/bins`` (memory: O(K)).

    ``path`` may also be a :class:`Recording` in memory (its arrays are not copied).
    """
    if isinstance(path, Recording):
        b = path.bins
        return RecordingHeader(path.system, np.asarray(path.shot_time, dtype=np.float64),
                               np.asarray(path.zero_crossings, dtype=np.float64),
                               np.asarray(path.rising, dtype=np.uint8), tuple(b.shape),
                               path.source)
    source = str(path)
    with h5.open_h5(path) as f:
        hdr = validate_recording_file(f, source, check_codes=check_codes)
    # what processing allocates per pixel: raw, signal and noise histograms (int64)
    H, W = hdr.shape[1:]
    n_bins = hdr.system.tdc.n_bins
    check_allocation(3 * 8 * H * W * n_bins,
                     f"the histograms ({H}, {W}, {n_bins}) of the recording", source, "/system")
    return hdr


def read_system(path: str | os.PathLike | Recording) -> System:
    """The recorded ``/system`` of a recording (format attributes checked; O(1): the
    shots are not read — :func:`read_header` validates them).  A
    :class:`Recording` in memory gives its own ``system``."""
    if isinstance(path, Recording):
        return path.system
    source = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise FormatError(f"cannot open as HDF5 ({e})", source) from None
    with f:
        return validate_header(f, source)


def iter_shot_chunks(path: str | os.PathLike, chunk_shots: int = 4096,
                     start: int = 0, stop: int | None = None,
                     truth_labels: bool = False) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Yield ``(first_shot, time (k,), bins (k, H, W))`` chunks of a recording.

    Memory is bounded by the chunk, whatever the recording's length.  Codes
    above n_bins raise :class:`FormatError` for the chunk that holds them.
    With ``truth_labels`` a fourth item, the chunk of ``/truth/label`` (or
    None), is yielded.  Chunks end at multiples of ``chunk_shots`` (rounded down to
    whole chunks of the file's storage) counted from shot 0, so the first chunk of a
    range that starts elsewhere is shorter.  ``path`` may also be a :class:`Recording` in memory
    (the chunks are views of its arrays).

    Examples
    --------
    >>> for first, times, bins in ms.iter_shot_chunks(ms.data.path("room.h5"), chunk_shots=256):
    ...     print(first, times.shape, bins.shape)
    0 (256,) (256, 1, 192)
    256 (256,) (256, 1, 192)
    512 (256,) (256, 1, 192)
    768 (32,) (32, 1, 192)
    """
    if isinstance(path, Recording):
        yield from _iter_memory_chunks(path, chunk_shots, start, stop, truth_labels)
        return
    source = str(path)
    if isinstance(chunk_shots, bool) or not isinstance(chunk_shots, (int, np.integer)) \
            or chunk_shots < 1:
        raise FormatError(f"expected a positive number of shots, found {chunk_shots!r}",
                          field="chunk_shots")
    with h5.open_h5(path) as f:
        system = validate_header(f, source)
        t_all = h5.dataset(f, "/shots/time", source)
        b_ds = h5.dataset(f, "/shots/bins", source)
        w, h = system.receiver.image_size
        h5.require_shape(t_all, (None,), source, "(K,)")
        h5.require_shape(b_ds, (t_all.shape[0], h, w), source,
                         f"(K, H, W) = ({t_all.shape[0]}, {h}, {w})")
        check_allocation(4 * min(chunk_shots, max(b_ds.shape[0], 1)) * h * w * 8,
                         f"chunks of {chunk_shots} shots", source, "--chunk-shots")
        lab = None
        if truth_labels and "truth" in f:
            check_truth(f, b_ds, source)
            lab = f["/truth/label"] if "label" in f["truth"] else None
        n = b_ds.shape[0] if stop is None else min(stop, b_ds.shape[0])
        # gzip'd chunks inflated by libdeflate where the system has it (faster than
        # zlib, the same bytes; io.deflate_chunks), else read by h5py
        fast = chunk_reader(b_ds)
        # blocks end at multiples of ``step`` counted from shot 0, a whole number of the
        # file's chunks: a range that starts inside a chunk (a Dask part's) reads each
        # stored chunk once, not once for each block it would straddle
        c = int(b_ds.chunks[0]) if b_ds.chunks else 1
        step = chunk_shots - chunk_shots % c if chunk_shots >= c else chunk_shots
        s0 = start
        while s0 < n:
            s1 = min(n, (s0 // step + 1) * step)
            blk = (fast.read(s0, s1) if fast is not None
                   else h5.read(b_ds, source, np.s_[s0:s1]))
            if blk.size and int(blk.max()) > system.tdc.n_bins:
                raise FormatError(f"expected codes 0..{system.tdc.n_bins} (n_bins), found "
                                  f"{int(blk.max())} in shots {s0}..{s1 - 1}", source,
                                  "/shots/bins")
            item = (s0, h5.read(t_all, source, np.s_[s0:s1]).astype(np.float64), blk)
            if truth_labels:
                labs = h5.read(lab, source, np.s_[s0:s1]) if lab is not None else None
                if labs is not None:
                    check_label_values(labs, source, s0)
                item = item + (labs,)
            yield item
            s0 = s1


def _iter_memory_chunks(rec: Recording, chunk_shots: int, start: int, stop: int | None,
                        truth_labels: bool):
    """:func:`iter_shot_chunks` over a :class:`Recording` in memory."""
    n_bins = rec.system.tdc.n_bins
    lab = rec.truth.get("label") if truth_labels else None
    n = rec.bins.shape[0] if stop is None else min(stop, rec.bins.shape[0])
    for s0 in range(start, n, chunk_shots):
        s1 = min(n, s0 + chunk_shots)
        blk = np.asarray(rec.bins[s0:s1])
        if blk.dtype != np.uint16:
            raise FormatError(f"expected dtype uint16, found {blk.dtype}", rec.source,
                              "/shots/bins")
        if blk.size and int(blk.max()) > n_bins:
            raise FormatError(f"expected codes 0..{n_bins} (n_bins), found {int(blk.max())} "
                              f"in shots {s0}..{s1 - 1}", rec.source, "/shots/bins")
        item = (s0, np.asarray(rec.shot_time[s0:s1], dtype=np.float64), blk)
        if truth_labels:
            item = item + ((np.asarray(lab[s0:s1]) if lab is not None else None),)
        yield item


def write_recording(path: str | os.PathLike, system: System, shot_time, bins,
                    zero_crossings, rising, truth: dict | None = None,
                    compression: str | None = "gzip") -> Path:
    """Write a FORMAT v1 recording atomically.

    Parameters
    ----------
    shot_time : (K,) float64 s; bins : (K, H, W) uint16; zero_crossings : (Z,)
    float64 s; rising : (Z,) uint8; truth : optional dict of arrays written
    under ``/truth``.  The inputs are validated as on read.

    Examples
    --------
    >>> import os, tempfile
    >>> rec = ms.read_recording(ms.data.path("room.h5"))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = ms.write_recording(os.path.join(folder, "copy.h5"), rec.system, rec.shot_time,
    ...                               rec.bins, rec.zero_crossings, rec.rising)
    ...     copy = ms.read_recording(path)
    ...     print(copy.bins.shape, bool(np.array_equal(copy.bins, rec.bins)))
    (800, 1, 192) True
    """
    t = np.asarray(shot_time, dtype=np.float64)
    b = np.asarray(bins)
    if b.dtype != np.uint16:
        raise FormatError(f"expected dtype uint16, found {b.dtype}", str(path), "/shots/bins")
    w, h = system.receiver.image_size
    if b.shape != (t.size, h, w):
        raise FormatError(f"expected shape ({t.size}, {h}, {w}), found {b.shape}", str(path),
                          "/shots/bins")
    zc, r = validate_zero_crossings(zero_crossings, rising, source=str(path))
    opts = {"compression": compression} if compression else {}
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["version"] = FORMAT_VERSION
        f.create_dataset("system", data=system_to_json(system))
        f.create_dataset("shots/time", data=t)
        chunks = (max(1, min(t.size, 1024)), h, w) if t.size else None
        f.create_dataset("shots/bins", data=b, chunks=chunks, **(opts if t.size else {}))
        f.create_dataset("scanner/zero_crossings", data=zc)
        f.create_dataset("scanner/rising", data=r.astype(np.uint8))
        for k, v in (truth or {}).items():
            v = np.asarray(v)
            f.create_dataset(f"truth/{k}", data=v, **(opts if v.ndim >= 2 and v.size else {}))
    return Path(path)


class RecordingWriter:
    """Write a FORMAT v1 recording chunk by chunk (for recordings larger than memory).

    Use as a context manager; the file appears (atomically) only when the
    block exits without error and every shot was written::

        with RecordingWriter(path, system, n_shots, zero_crossings, rising) as w:
            for t, bins in chunks:
                w.append(t, bins)

    ``compression`` : None (fastest) or an h5py filter name such as "gzip".
    """

    def __init__(self, path, system: System, n_shots: int, zero_crossings, rising,
                 compression: str | None = None, chunk_shots: int = 4096):
        self.path = Path(path)
        self.system = system
        self.n_shots = int(n_shots)
        self.zc, self.rising = validate_zero_crossings(zero_crossings, rising, str(path))
        self.compression = compression
        self.chunk_shots = chunk_shots
        self._written = 0
        self._last_time = -np.inf

    def __enter__(self):
        self._ctx = atomic_output(self.path)
        tmp = self._ctx.__enter__()
        try:
            self._f = h5py.File(tmp, "w")
            w, h = self.system.receiver.image_size
            f = self._f
            f.attrs["format"] = FORMAT_NAME
            f.attrs["version"] = FORMAT_VERSION
            f.create_dataset("system", data=system_to_json(self.system))
            self._t = f.create_dataset("shots/time", shape=(self.n_shots,), dtype=np.float64)
            self._b = f.create_dataset("shots/bins", shape=(self.n_shots, h, w), dtype=np.uint16,
                                       chunks=(max(1, min(self.n_shots, self.chunk_shots)), h, w),
                                       compression=self.compression)
            f.create_dataset("scanner/zero_crossings", data=self.zc)
            f.create_dataset("scanner/rising", data=self.rising.astype(np.uint8))
        except BaseException as e:
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise
        return self

    def append(self, shot_time, bins) -> None:
        """Add the next shots: (k,) float64 s, increasing; (k, H, W) uint16."""
        t = np.asarray(shot_time, dtype=np.float64)
        b = np.asarray(bins)
        k = t.size
        if b.dtype != np.uint16 or b.shape != (k,) + self._b.shape[1:]:
            raise FormatError(f"expected uint16 bins of shape {(k,) + self._b.shape[1:]}, found "
                              f"{b.dtype} {b.shape}", str(self.path), "/shots/bins")
        if self._written + k > self.n_shots:
            raise FormatError(f"more than the declared {self.n_shots} shots", str(self.path),
                              "/shots/time")
        if k and (t[0] <= self._last_time or np.any(np.diff(t) <= 0)):
            raise FormatError("expected strictly increasing shot times", str(self.path),
                              "/shots/time")
        self._t[self._written:self._written + k] = t
        self._b[self._written:self._written + k] = b
        self._written += k
        if k:
            self._last_time = float(t[-1])

    def __exit__(self, exc_type, exc, tb):
        self._f.close()
        if exc_type is None and self._written != self.n_shots:
            exc = FormatError(f"{self._written} shots written, {self.n_shots} declared",
                              str(self.path), "/shots/time")
            self._ctx.__exit__(FormatError, exc, None)
            raise exc
        return self._ctx.__exit__(exc_type, exc, tb)
