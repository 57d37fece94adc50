"""Live sources of shots: what a lidar driver's ``open_source`` is to its sensor.

Every source is an iterator of :class:`~mems_stereo.io.recording.Recording` chunks of
consecutive shots of one acquisition, the form
:class:`mems_stereo.pipeline.frames.FrameProcessor` takes: the source's ``system``
(known when it opens), shot times (k,) float64 s strictly increasing across chunks,
bins (k, H, W) uint16, and the zero crossings known near the chunk's shots (repeats
across chunks are harmless).  A shot is released only once a zero crossing at or
after its time is known (so its scan angle, and those of every frame it closes, can
be computed); the end of the stream releases the rest.

Sources (``mems-stereo live``, docs/live.md):

- :class:`ReplaySource`: a FORMAT v1 recording replayed at ``rate`` times its own
  clock (``None``: as fast as it is read).
- :class:`~mems_stereo.io.live_h5.GrowingH5Source`: a recording being written
  (HDF5 single-writer/multiple-reader).
- :class:`~mems_stereo.io.live_zmq.ZmqSource`: shot chunks on a ZeroMQ socket.
- :class:`~mems_stereo.io.live_ptu.PtuTailSource`: a PicoQuant PTU file being written.

Each source has ``stop()`` (thread-safe: the iteration ends at its next wait),
``can_wait`` (True where the data waits for a slow consumer without loss, so a
consumer may block instead of dropping frames) and :meth:`LiveSource.due` (the wall
time at which a recording time is due, for paced replays).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import numpy as np

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.recording import Recording, iter_shot_chunks, read_header
from mems_stereo.model.system import System

#: recording seconds per chunk of a paced replay (bounds the added latency)
PIECE_SECONDS = 0.005


class LiveSource:
    """Base of the live sources: ``system``, ``source`` (a name for messages), ``stop()``.

    Subclasses implement :meth:`chunks`; iterating the source iterates it.  ``ended``
    says why the stream ended (``"finished"``, ``"idle"``, ``"stopped"``) once it has.
    """

    #: a consumer may block (the data waits without loss) instead of dropping frames
    can_wait = False

    def __init__(self, system: System, source: str):
        self.system = system
        self.source = source
        self.ended: str | None = None
        self._stop = threading.Event()

    def stop(self) -> None:
        """End the iteration at its next wait (any thread)."""
        self._stop.set()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def due(self, t: float) -> float | None:
        """Wall time (``time.monotonic``) at which recording time ``t`` (s) is due, or None
        where the source is not paced (latency is then measured from arrival)."""
        return None

    def chunks(self) -> Iterator[Recording]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Recording]:
        return self.chunks()

    def chunk(self, times, bins, zc, rising) -> Recording:
        """A Recording chunk of this source (arrays as given)."""
        return Recording(self.system, times, bins, zc, rising, {}, self.source)


def check_codes(bins: np.ndarray, system: System, source: str, what: str) -> None:
    """Refuse TDC codes above n_bins (:class:`FormatError` naming ``what``)."""
    n = system.tdc.n_bins
    if bins.size and int(bins.max()) > n:
        raise FormatError(f"expected codes 0..{n} (n_bins), found {int(bins.max())} in {what}",
                          source, "/shots/bins")


class ShotRelease:
    """Shots held until a zero crossing at or after their time is known.

    ``add`` new shots and crossings (any order between the two); ``take`` returns
    the releasable shots as ``(times, bins, zc, rising)`` with the crossings within
    two mechanical periods of them, or None.  Memory: the held shots and the
    crossings not yet behind the released shots.
    """

    def __init__(self, system: System, source: str):
        h, w = system.receiver.height, system.receiver.width
        self.margin = 2.0 / float(system.scanner.f_mech)
        self.source = source
        self.times = np.zeros(0)
        self.bins = np.zeros((0, h, w), np.uint16)
        self.zc = np.zeros(0)
        self.rising = np.zeros(0, np.uint8)
        self.last_time = -np.inf

    def add(self, times=None, bins=None, zc=None, rising=None) -> None:
        if zc is not None and np.size(zc):
            zc = np.asarray(zc, np.float64).ravel()
            ri = np.asarray(rising, np.uint8).ravel()
            if ri.shape != zc.shape:
                raise FormatError(f"expected one rising flag per zero crossing ({zc.size}), "
                                  f"found {ri.size}", self.source, "/scanner/rising")
            if not np.all(np.isfinite(zc)) or np.any(np.diff(zc) <= 0) or (
                    self.zc.size and zc[0] <= self.zc[-1]):
                raise FormatError("expected finite zero crossings, strictly increasing across "
                                  "chunks", self.source, "/scanner/zero_crossings")
            self.zc = np.concatenate([self.zc, zc])
            self.rising = np.concatenate([self.rising, ri])
        if times is not None and np.size(times):
            t = np.asarray(times, np.float64).ravel()
            if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0) or t[0] <= self.last_time:
                raise FormatError("expected finite shot times, strictly increasing across "
                                  "chunks", self.source, "/shots/time")
            self.last_time = float(t[-1])
            self.times = np.concatenate([self.times, t])
            self.bins = np.concatenate([self.bins, np.asarray(bins, np.uint16)])

    def take(self, final: bool = False):
        """``(times, bins, zc, rising)`` of the shots now releasable (all with ``final``),
        or None when there are none."""
        if final:
            k = self.times.size
        else:
            upto = self.zc[-1] if self.zc.size else -np.inf
            k = int(np.searchsorted(self.times, upto, side="right"))
        if k == 0:
            return None
        t, b = self.times[:k], self.bins[:k]
        lo = int(np.searchsorted(self.zc, t[0] - self.margin))
        hi = int(np.searchsorted(self.zc, t[-1] + self.margin, side="right"))
        out = (t, b, self.zc[lo:hi].copy(), self.rising[lo:hi].copy())
        self.times, self.bins = self.times[k:], self.bins[k:]
        keep = int(np.searchsorted(self.zc, t[-1] - self.margin))
        self.zc, self.rising = self.zc[keep:], self.rising[keep:]
        return out


class ReplaySource(LiveSource):
    """A FORMAT v1 recording replayed as a live stream.

    ``rate`` : recording seconds per wall second (1: real time, paced by the
    recording's shot times), or None: as fast as it is read (and the consumer may
    make the reader wait: ``can_wait``).  ``chunk_shots`` : shots read at a time;
    a paced replay hands them on in pieces of :data:`PIECE_SECONDS` of recording
    time, each when its last shot is due.  ``start``/``stop_shot`` : a range of shots.
    """

    def __init__(self, path: str | os.PathLike | Recording, rate: float | None = None,
                 chunk_shots: int = 8192, start: int = 0, stop_shot: int | None = None):
        if rate is not None and not (np.isfinite(rate) and rate > 0):
            raise OptionError(f"expected a positive rate or 'max', found {rate!r}", field="--rate")
        src = path if isinstance(path, Recording) else os.fspath(path)
        hdr = read_header(src)
        super().__init__(hdr.system, path.source if isinstance(path, Recording) else src)
        self.path = src
        self.rate = rate
        self.can_wait = rate is None
        self.chunk_shots = int(chunk_shots)
        self.range = (int(start), stop_shot)
        self.zero_crossings, self.rising = hdr.zero_crossings, hdr.rising
        self.t_first = float(hdr.shot_time[start]) if hdr.shot_time.size > start else 0.0
        self.wall0: float | None = None
        self.margin = 2.0 / float(hdr.system.scanner.f_mech)

    def due(self, t: float) -> float | None:
        if self.rate is None or self.wall0 is None:
            return None
        return self.wall0 + (t - self.t_first) / self.rate

    def _pieces(self, times: np.ndarray):
        """Slices of a chunk's shots, :data:`PIECE_SECONDS` each when paced."""
        if self.rate is None:
            yield slice(0, times.size)
            return
        edges = np.searchsorted(times, np.arange(times[0], times[-1], PIECE_SECONDS)[1:])
        bounds = [0, *edges.tolist(), times.size]
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b > a:
                yield slice(a, b)

    def chunks(self) -> Iterator[Recording]:
        zc, ri, m = self.zero_crossings, self.rising, self.margin
        self.wall0 = time.monotonic()
        for _first, times, bins in iter_shot_chunks(self.path, self.chunk_shots,
                                                    self.range[0], self.range[1]):
            for s in self._pieces(times):
                t = times[s]
                wait = self.due(float(t[-1]))
                if wait is not None and self._stop.wait(max(0.0, wait - time.monotonic())):
                    break
                if self.stopped:
                    break
                lo = int(np.searchsorted(zc, t[0] - m))
                hi = int(np.searchsorted(zc, t[-1] + m, side="right"))
                yield self.chunk(t, bins[s], zc[lo:hi], ri[lo:hi])
            if self.stopped:
                self.ended = "stopped"
                return
        self.ended = "finished"


def parse_rate(text: str) -> float | None:
    """``--rate``: ``max`` → None, else a positive number (recording s per wall s)."""
    if str(text).strip().lower() == "max":
        return None
    try:
        r = float(text)
    except ValueError:
        r = float("nan")
    if not (np.isfinite(r) and r > 0):
        raise OptionError(f"expected a positive number or 'max', found {text!r}", field="--rate")
    return r
