"""A FORMAT v1 recording that grows while it is read: HDF5 single-writer/multiple-reader.

An acquisition program writes the recording as it records (:class:`LiveRecordingWriter`,
or any HDF5 library with SWMR: the layout below); ``mems-stereo live REC.h5``
follows it (:class:`GrowingH5Source`).  The file is FORMAT v1 (docs/formats.md) with
every dataset extendible, plus a counter that says how much of it is complete:

| path | type, shape | meaning |
| --- | --- | --- |
| ``/shots/time``, ``/shots/bins`` | as FORMAT v1, chunked, first axis unlimited | the shots |
| ``/scanner/zero_crossings``, ``/scanner/rising`` | as FORMAT v1, unlimited | the crossings |
| ``/live/state`` | int64 [3] | shots written, zero crossings written, 1 when finished |

The writer flushes the data before it raises ``/live/state`` (and flushes that), so a
reader never reads past it: a shot or crossing half written is waited for, never read
as data.  When the writer closes, the datasets hold exactly the counted items and the
file reads as an ordinary recording.  A file without ``/live/state`` is read as
finished.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from mems_stereo.errors import FormatError
from mems_stereo.io import hdf5 as h5
from mems_stereo.io.live_sources import LiveSource, ShotRelease, check_codes
from mems_stereo.io.recording import Recording
from mems_stereo.io.recording_checks import FORMAT_NAME, FORMAT_VERSION, validate_header
from mems_stereo.model.system import System, system_to_json

#: seconds between looks at a growing file
POLL_SECONDS = 0.005
STATE = "/live/state"


class LiveRecordingWriter:
    """Write a recording that :class:`GrowingH5Source` (or any SWMR reader) follows.

    Use as a context manager; :meth:`append` shots and zero crossings as they are
    recorded, in time order; closing marks the file finished (also after an error, so
    a reader ends)::

        with LiveRecordingWriter(path, system) as w:
            w.append(shot_time, bins, zero_crossings, rising)

    ``chunk_shots`` : shots per HDF5 chunk; ``compression`` : None or "gzip".  The file
    is written in place (a reader must see it while it grows), not atomically.
    """

    def __init__(self, path, system: System, chunk_shots: int = 1024,
                 compression: str | None = None):
        self.path = Path(path)
        self.system = system
        self.chunk_shots = max(1, int(chunk_shots))
        self.compression = compression
        self.n_shots = self.n_zc = 0
        self._last_t = self._last_z = -np.inf

    def __enter__(self):
        w, h = self.system.receiver.image_size
        f = self._f = h5py.File(self.path, "w", libver="latest")
        f.attrs["format"] = FORMAT_NAME
        f.attrs["version"] = FORMAT_VERSION
        f.create_dataset("system", data=system_to_json(self.system))
        c = self.chunk_shots
        self._t = f.create_dataset("shots/time", (0,), np.float64, maxshape=(None,),
                                   chunks=(c,))
        self._b = f.create_dataset("shots/bins", (0, h, w), np.uint16, maxshape=(None, h, w),
                                   chunks=(c, h, w), compression=self.compression)
        self._z = f.create_dataset("scanner/zero_crossings", (0,), np.float64,
                                   maxshape=(None,), chunks=(1024,))
        self._r = f.create_dataset("scanner/rising", (0,), np.uint8, maxshape=(None,),
                                   chunks=(1024,))
        self._s = f.create_dataset(STATE, data=np.zeros(3, np.int64))
        f.swmr_mode = True
        return self

    def _grow(self, ds, data, n: int) -> None:
        ds.resize((n + len(data),) + ds.shape[1:])
        ds[n:] = data

    def append(self, shot_time=(), bins=None, zero_crossings=(), rising=()) -> None:
        """Add shots ((k,) float64 s increasing, (k, H, W) uint16) and/or zero crossings
        ((z,) float64 s increasing, (z,) 0/1); then publish them to readers."""
        t = np.asarray(shot_time, np.float64).ravel()
        zc = np.asarray(zero_crossings, np.float64).ravel()
        ri = np.asarray(rising, np.uint8).ravel()
        if t.size:
            b = np.asarray(bins)
            if b.dtype != np.uint16 or b.shape != (t.size,) + self._b.shape[1:]:
                raise FormatError(f"expected uint16 bins of shape {(t.size,) + self._b.shape[1:]}"
                                  f", found {b.dtype} {b.shape}", str(self.path), "/shots/bins")
            if t[0] <= self._last_t or np.any(np.diff(t) <= 0):
                raise FormatError("expected strictly increasing shot times", str(self.path),
                                  "/shots/time")
            self._grow(self._t, t, self.n_shots)
            self._grow(self._b, b, self.n_shots)
            self.n_shots += t.size
            self._last_t = float(t[-1])
        if zc.size:
            if ri.shape != zc.shape or zc[0] <= self._last_z or np.any(np.diff(zc) <= 0):
                raise FormatError("expected strictly increasing zero crossings, one rising "
                                  "flag each", str(self.path), "/scanner/zero_crossings")
            self._grow(self._z, zc, self.n_zc)
            self._grow(self._r, ri, self.n_zc)
            self.n_zc += zc.size
            self._last_z = float(zc[-1])
        self._publish(0)

    def _publish(self, finished: int) -> None:
        self._f.flush()  # the data first: a reader trusts every item the state counts
        self._s[...] = np.array([self.n_shots, self.n_zc, finished], np.int64)
        self._s.flush()

    def close(self) -> None:
        """Mark the recording finished and close it."""
        if self._f is not None:
            try:
                self._publish(1)
            finally:
                self._f.close()
                self._f = None

    def __exit__(self, *exc):
        self.close()
        return False


class GrowingH5Source(LiveSource):
    """Follow a recording being written (see the module doc); yields Recording chunks of
    at most ``chunk_shots`` shots as they appear.

    Ends when the writer marks the file finished, after ``idle_timeout`` s (None:
    never) without a new shot, or at :meth:`stop`.  A file written without SWMR, or
    without ``/live/state``, is read whole as a finished recording.
    """

    can_wait = False

    def __init__(self, path: str | os.PathLike, idle_timeout: float | None = 10.0,
                 chunk_shots: int = 4096):
        source = str(path)
        self.path = path
        self.idle_timeout = idle_timeout
        self.chunk_shots = int(chunk_shots)
        self._f = self._open(path, source)
        super().__init__(validate_header(self._f, source), source)

    @staticmethod
    def _open(path, source: str) -> h5py.File:
        h5.open_h5(path).close()  # the package's checks: a regular file, no external links
        try:
            return h5py.File(path, "r", libver="latest", swmr=True)
        except OSError:
            try:  # not written for SWMR: an ordinary (finished) recording
                return h5py.File(path, "r")
            except OSError as e:
                raise FormatError(f"cannot open as HDF5 ({e})", source) from None

    def _state(self) -> tuple[int, int, bool]:
        ds = [h5.dataset(self._f, p, self.source) for p in
              ("/shots/time", "/shots/bins", "/scanner/zero_crossings", "/scanner/rising")]
        if STATE not in self._f:
            return min(ds[0].shape[0], ds[1].shape[0]), ds[2].shape[0], True
        st = self._f[STATE]
        st.refresh()
        v = np.asarray(st[...], np.int64).ravel()
        if v.size != 3 or np.any(v < 0):
            raise FormatError(f"expected 3 non-negative counts, found {v.tolist()}", self.source,
                              STATE)
        for d in ds:
            d.refresh()
        n, z = int(v[0]), int(v[1])
        if n > min(ds[0].shape[0], ds[1].shape[0]) or z > min(ds[2].shape[0], ds[3].shape[0]):
            raise FormatError(f"counts {n} shots, {z} zero crossings beyond the datasets' "
                              "lengths", self.source, STATE)
        return n, z, bool(v[2])

    def _unpublished(self, n: int, z: int) -> str:
        """Items in the datasets past the counts of ``/live/state`` (an append whose
        writer stopped before publishing it: never read), as words for ``ended``."""
        if STATE not in self._f:
            return ""
        ds = [self._f[p] for p in ("/shots/time", "/shots/bins", "/scanner/zero_crossings",
                                   "/scanner/rising")]
        for d in ds:
            d.refresh()
        extra = (max(ds[0].shape[0], ds[1].shape[0]) - n, max(ds[2].shape[0], ds[3].shape[0]) - z)
        if max(extra) <= 0:
            return ""
        return (f" ({extra[0]} shots, {extra[1]} zero crossings past {STATE}'s counts left "
                "unread: an append not published)")

    def _read(self, rel: ShotRelease, n0: int, n: int, z0: int, z: int) -> None:
        f, src = self._f, self.source
        if z > z0:
            rel.add(zc=h5.read(f["/scanner/zero_crossings"], src, np.s_[z0:z]),
                    rising=h5.read(f["/scanner/rising"], src, np.s_[z0:z]))
        if n > n0:
            bins = h5.read(f["/shots/bins"], src, np.s_[n0:n])
            check_codes(bins, self.system, src, f"shots {n0}..{n - 1}")
            rel.add(times=h5.read(f["/shots/time"], src, np.s_[n0:n]), bins=bins)

    def chunks(self) -> Iterator[Recording]:
        rel = ShotRelease(self.system, self.source)
        n0 = z0 = 0
        last_new = time.monotonic()
        try:
            while not self.stopped:
                n_all, z, done = self._state()
                n = min(n_all, n0 + self.chunk_shots)
                if n > n0 or z > z0:
                    self._read(rel, n0, n, z0, z)
                    n0, z0, last_new = n, z, time.monotonic()
                final = done and n0 >= n_all
                idle = (self.idle_timeout is not None
                        and time.monotonic() - last_new > self.idle_timeout)
                got = rel.take(final=final or idle)
                if got is not None:
                    yield self.chunk(*got)
                if final or idle:
                    self.ended = "finished" if final else "idle" + self._unpublished(n0, z0)
                    return
                if got is None:
                    self._stop.wait(POLL_SECONDS)
            self.ended = "stopped"
        finally:
            self._f.close()
