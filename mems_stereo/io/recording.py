"""HDF5 recordings of FORMAT v1: read, validate, write, and read in chunks of shots.

A recording holds one frame or run: the system description as known when
recording (``/system``), the shot trigger times and TDC codes
(``/shots/time``, ``/shots/bins``), the zero crossings of θ_mech
(``/scanner/zero_crossings``, ``/scanner/rising``), and for simulated data a
``/truth`` group that processing never reads.

Errors are :class:`~mems_stereo.errors.FormatError` naming the file, the
dataset and what was wrong.  Writers are atomic (``io_util.atomic_output``).
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
from mems_stereo.model.scanner import crossing_phases, validate_zero_crossings
from mems_stereo.model.system import System, system_from_json, system_to_json
from mems_stereo.util.atomic import atomic_output
from mems_stereo.util.limits import check_allocation

#: Accepted deviation of the mirror frequency implied by the zero crossings
#: (median over the recording) from the system's ``scanner.f_mech``.
CROSSING_FREQUENCY_TOLERANCE = 0.25

FORMAT_NAME = "mems-stereo/recording"
FORMAT_VERSION = 1
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


def _need(f: h5py.File, path: str, source: str, whole: bool = False) -> h5py.Dataset:
    return h5.dataset(f, path, source, whole=whole)


def _check_dtype(ds, kinds: str, expected: str, source: str, path: str):
    if ds.dtype.kind not in kinds:
        raise FormatError(f"expected {expected}, found dtype {ds.dtype}", source, path)


def validate_header(f: h5py.File, source: str, scan_axes: int = 1) -> System:
    """Check the file attributes and ``/system``; return the recorded System.

    ``scan_axes`` : 1 (FORMAT v1; the attribute absent or 1) or 2 (the
    two-axis extension, :mod:`mems_stereo.io.recording2d`; the attribute 2).
    """
    h5.require_format(f, FORMAT_NAME, FORMAT_VERSION, source)
    if "scan_axes" in f.attrs or scan_axes != 1:  # the two-axis extension (formats.md §5)
        try:
            axes = h5.attr_int(f, "scan_axes", source)
        except FormatError:
            axes = -1
        axes = 1 if axes is None else axes
        if axes != scan_axes and scan_axes == 1 and axes == 2:
            raise FormatError("a two-axis recording (scan_axes = 2): read it with "
                              "mems_stereo.io.recording2d.read_recording_2d", source,
                              "attrs/scan_axes")
        if axes != scan_axes:
            raise FormatError(f"expected attribute scan_axes = {scan_axes}, found "
                              f"{h5.shown_attr(f, 'scan_axes')}", source, "attrs/scan_axes")
    ds = _need(f, "/system", source)
    if ds.shape != () or ds.dtype.kind not in "OSU":
        raise FormatError(f"expected a scalar JSON string, found {ds.dtype} {ds.shape}", source,
                          "/system")
    raw = h5.read(ds, source)
    if isinstance(raw, bytes):
        try:
            raw = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError("expected UTF-8 JSON text, found undecodable bytes", source,
                              "/system") from None
    if not isinstance(raw, str):
        raise FormatError(f"expected a JSON string, found {type(raw).__name__}", source,
                          "/system")
    return system_from_json(raw, source=f"{source}:/system")


def check_crossing_frequency(zc: np.ndarray, rising: np.ndarray, f_mech: float,
                             source: str = "", tol: float = CROSSING_FREQUENCY_TOLERANCE,
                             field: str = "/scanner/zero_crossings"):
    """Cross-check the zero crossings against ``f_mech`` (Hz).

    Between crossings the phase advances by π (alternating kinds) or 2π (same
    kind: one was missed); the median frequency this implies must lie within
    ``tol`` of ``f_mech``.  Crossings spaced for another frequency, or all of
    one kind (which doubles the implied frequency), raise FormatError.
    """
    if zc.size < 3:
        return
    f_implied = np.diff(crossing_phases(zc, rising)) / (2 * np.pi * np.diff(zc))
    med = float(np.median(f_implied))
    if not abs(med / f_mech - 1.0) <= tol:
        kinds = "all rising" if rising.all() else ("all falling" if not rising.any() else "")
        raise FormatError(f"the crossings imply a mirror frequency of {med:.6g} Hz, but "
                          f"scanner.f_mech = {f_mech:g} Hz (/system)"
                          + (f"; the crossings are {kinds}" if kinds else ""),
                          source, field)


def read_shot_times(f: h5py.File, source: str) -> np.ndarray:
    """``/shots/time``: (K,) float64 s, finite, strictly increasing (checked in blocks;
    the per-shot arrays of a run are checked against the memory budget first)."""
    t_ds = _need(f, "/shots/time", source, whole=True)
    if t_ds.dtype != np.float64:
        raise FormatError(f"expected float64 seconds, found dtype {t_ds.dtype}", source,
                          "/shots/time")
    if t_ds.ndim != 1:
        raise FormatError(f"expected shape (K,), found {t_ds.shape}", source, "/shots/time")
    # O(K) arrays of the run (angles, steps, indices): a few float64 per shot
    check_allocation(16 * t_ds.size * 8, f"per-shot arrays of {t_ds.size} shots", source,
                     "/shots/time")
    t = np.asarray(h5.read(t_ds, source), dtype=np.float64)
    block = 1 << 20  # checked in blocks: small temporaries for long recordings
    for a in range(0, t.size, block):
        tb = t[a:a + block + 1]
        if not np.all(np.isfinite(tb)):
            raise FormatError("expected finite times, found NaN or inf", source, "/shots/time")
        bad = np.diff(tb) <= 0
        if bad.any():
            i = a + int(np.argmax(bad))
            raise FormatError(f"expected strictly increasing shot times, found t[{i + 1}] = "
                              f"{float(t[i + 1])!r} <= t[{i}] = {float(t[i])!r}", source,
                              "/shots/time")
    return t


def read_crossings(f: h5py.File, source: str, f_mech: float, group: str = "/scanner"):
    """``GROUP/zero_crossings`` (float64 s) and ``GROUP/rising`` (0/1) of a resonant
    axis, validated and cross-checked against its ``f_mech`` (Hz); returns
    ``(zc (Z,) float64, rising (Z,) uint8)``."""
    zpath, rpath = f"{group}/zero_crossings", f"{group}/rising"
    zc_ds = _need(f, zpath, source, whole=True)
    if zc_ds.dtype != np.float64:
        raise FormatError(f"expected float64 seconds, found dtype {zc_ds.dtype}", source, zpath)
    r_ds = _need(f, rpath, source, whole=True)
    _check_dtype(r_ds, "iub", "uint8 0/1", source, rpath)
    zc, rising = validate_zero_crossings(h5.read(zc_ds, source), h5.read(r_ds, source),
                                         source=source, field=zpath)
    check_crossing_frequency(zc, rising, f_mech, source, field=zpath)
    return zc, rising.astype(np.uint8)


def validate_recording_file(f: h5py.File, source: str, check_codes: bool = True,
                            chunk_shots: int = 4096):
    """Validate the datasets of an open recording against FORMAT v1.

    Returns ``(system, shot_time, zero_crossings, rising)``; ``/shots/bins`` is
    checked for shape and dtype and, if ``check_codes``, streamed to check
    that every code is <= n_bins (memory bounded by ``chunk_shots``).
    """
    system = validate_header(f, source)
    t = read_shot_times(f, source)
    b_ds = _need(f, "/shots/bins", source)
    w, h = system.receiver.image_size
    if b_ds.ndim != 3 or b_ds.shape[0] != t.size or b_ds.shape[1:] != (h, w):
        raise FormatError(f"expected shape (K, H, W) = ({t.size}, {h}, {w}), found {b_ds.shape}",
                          source, "/shots/bins")
    if b_ds.dtype != np.uint16:
        raise FormatError(f"expected dtype uint16, found {b_ds.dtype}", source, "/shots/bins")
    if check_codes:
        n_bins = system.tdc.n_bins
        for s0 in range(0, t.size, chunk_shots):
            blk = h5.read(b_ds, source, np.s_[s0:s0 + chunk_shots])
            if blk.size and int(blk.max()) > n_bins:
                k = s0 + int(np.argmax(blk.reshape(blk.shape[0], -1).max(axis=1) > n_bins))
                raise FormatError(f"expected codes 0..{n_bins} (n_bins), found "
                                  f"{int(blk.max())} in shot {k}", source, "/shots/bins")
    zc, rising = read_crossings(f, source, system.scanner.f_mech)
    _check_truth(f, b_ds, source)
    return system, t, zc, rising


def _check_truth(f: h5py.File, b_ds: h5py.Dataset, source: str) -> None:
    """``/truth`` is optional, but where ``/truth/label`` exists it must fit the bins."""
    if "truth" not in f:
        return
    if not isinstance(f["truth"], h5py.Group):
        raise FormatError("expected a group, found a dataset", source, "/truth")
    if "label" in f["truth"]:
        lab = _need(f, "/truth/label", source)
        if lab.shape != b_ds.shape or lab.dtype.kind not in "iu":
            raise FormatError(f"expected integer labels of shape {b_ds.shape} like /shots/bins,"
                              f" found {lab.dtype} {lab.shape}", source, "/truth/label")


def read_truth(f: h5py.File, source: str = "", attrs: bool = False) -> dict:
    """The optional ``/truth`` group's datasets (and, with ``attrs``, its scalar
    attributes) as a dict; anything but a group there is ignored (processing
    never reads the truth)."""
    truth = {}
    try:
        g = f["truth"] if "truth" in f else None
    except h5.H5_ERRORS:
        g = None
    if isinstance(g, h5py.Group):
        for k in g:
            if isinstance(g.get(k), h5py.Dataset):
                ds = h5.dataset(f, f"/truth/{k}", source, whole=True)
                truth[k] = h5.read(ds, source)
        if attrs:
            try:
                truth.update({k: v for k, v in g.attrs.items()})
            except h5.H5_ERRORS as e:
                raise FormatError(f"cannot read the attributes ({e})", source,
                                  "/truth") from None
    return truth


def read_recording(path: str | os.PathLike, *, truth: bool = True) -> Recording:
    """Read and validate a whole recording into memory.

    For recordings larger than memory use :func:`iter_shot_chunks`.
    """
    source = str(path)
    with h5.open_h5(path) as f:
        system, t, zc, rising = validate_recording_file(f, source, check_codes=False)
        bins = h5.read(_need(f, "/shots/bins", source, whole=True), source)
        if bins.size and int(bins.max()) > system.tdc.n_bins:
            k = int(np.argmax(bins.reshape(bins.shape[0], -1).max(axis=1) > system.tdc.n_bins))
            raise FormatError(f"expected codes 0..{system.tdc.n_bins} (n_bins), found "
                              f"{int(bins.max())} in shot {k}", source, "/shots/bins")
        tr = read_truth(f, source) if truth else {}
    return Recording(system, t, bins, zc, rising, tr, source)


@dataclass
class RecordingHeader:
    """Everything of a recording except the bins: for streaming."""

    system: System
    shot_time: np.ndarray
    zero_crossings: np.ndarray
    rising: np.ndarray
    shape: tuple
    source: str


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
        system, t, zc, rising = validate_recording_file(f, source, check_codes=check_codes)
        shape = tuple(f["/shots/bins"].shape)
    # what processing allocates per pixel: raw, signal and noise histograms (int64)
    H, W = shape[1:]
    check_allocation(3 * 8 * H * W * system.tdc.n_bins,
                     f"the histograms ({H}, {W}, {system.tdc.n_bins}) of the recording",
                     source, "/system")
    return RecordingHeader(system, t, zc, rising, shape, source)


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
        t_all = _need(f, "/shots/time", source)
        b_ds = _need(f, "/shots/bins", source)
        w, h = system.receiver.image_size
        h5.require_shape(t_all, (None,), source, "(K,)")
        h5.require_shape(b_ds, (t_all.shape[0], h, w), source,
                         f"(K, H, W) = ({t_all.shape[0]}, {h}, {w})")
        check_allocation(4 * min(chunk_shots, max(b_ds.shape[0], 1)) * h * w * 8,
                         f"chunks of {chunk_shots} shots", source, "--chunk-shots")
        lab = None
        if truth_labels and "truth" in f:
            _check_truth(f, b_ds, source)
            lab = f["/truth/label"] if "label" in f["truth"] else None
        n = b_ds.shape[0] if stop is None else min(stop, b_ds.shape[0])
        # gzip'd chunks inflated by libdeflate where the system has it (twice zlib's
        # speed, the same bytes; io.deflate_chunks), else read by h5py
        from mems_stereo.io.deflate_chunks import chunk_reader

        fast = chunk_reader(b_ds)
        # blocks end at multiples of ``step`` counted from shot 0, a whole number of the
        # file's chunks: a range that starts inside a chunk (a Dask part's) reads each
        # stored chunk once, not twice (once for each block it would straddle: 0.1 s
        # more inflating in 0.8 s for the second half of a 1,600,000-shot recording)
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
                item = item + ((h5.read(lab, source, np.s_[s0:s1]) if lab is not None
                                else None),)
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
