"""Live frames: a source thread, a bounded queue of frames, processing and writing.

:class:`LiveRun` reads a live source (:mod:`mems_stereo.io.live_sources`) in a thread of
its own, cuts its shots at the frame boundaries of the
:class:`~mems_stereo.pipeline.frames.FrameProcessor` (the same frames as
``iter_frames``), and hands them through a queue to the caller's thread, which
processes them and writes each finished frame (``write(frame)``).

The queue is bounded in frames: at most ``max_queued`` admitted frames wait in it (a
frame leaves it when processing takes its first shots).  A frame whose first shot
arrives when it is full takes the place of the oldest waiting frame, which is dropped
whole (none of its shots reach the processor): the newest data is processed first, the
latency stays within about ``max_queued`` + 1 processing times, and every drop is
counted and listed by index, never silent, never a growing backlog.  A source whose data waits
without loss (a replay at ``--rate max``: ``source.can_wait``) makes the reader wait
instead, so nothing is dropped.  With a
:class:`~mems_stereo.pipeline.frame_workers.ParallelFrameProcessor` up to one frame per
worker is in flight besides the queue (processing waits for the oldest when all are
busy), and finished frames are written in order as the workers return them.

:meth:`LiveRun.stop` (a signal handler may call it) ends the run cleanly: the source
stops, the shots already queued are processed, and every frame whose shots were
complete is written; the partial frame is not.

Latency of a frame: wall time when its cloud was written minus the wall time its end
was due (a paced replay: :meth:`~mems_stereo.io.live_sources.LiveSource.due`) or,
where the source is not paced, when the shot that completed it arrived.
"""

from __future__ import annotations

import collections
import dataclasses
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mems_stereo.io.recording import Recording
from mems_stereo.pipeline.frames import Frame, FrameProcessor
from mems_stereo.util.memory import release_freed_memory

#: seconds the consumer waits on an empty queue before it looks at the stop flag
POLL = 0.05
#: the same while frames are in a worker process (how soon a finished one is written)
POLL_IN_FLIGHT = 0.004


@dataclass
class LiveStats:
    """What a live run did.

    frames_written : frames written.  dropped : indices of the frames dropped because
    processing was behind.  partial : frames not written because the run was stopped
    before their shots were complete.  latency : (frames_written,) s, see the module
    doc.  shots, shots_dropped : shots processed and dropped.  wall : s from start to
    the end.  ended : why the stream ended ("finished", "idle", "stopped").
    written_at : (frames_written,) wall seconds since the start at which each frame
    was written.
    """

    frames_written: int = 0
    dropped: list = field(default_factory=list)
    partial: int = 0
    latency: list = field(default_factory=list)
    written_at: list = field(default_factory=list)
    shots: int = 0
    shots_dropped: int = 0
    wall: float = 0.0
    ended: str = ""

    @property
    def frames_dropped(self) -> int:
        return len(self.dropped)

    def latency_text(self) -> str:
        """``latency median 12 ms, p99 30 ms, max 31 ms`` (empty without frames)."""
        if not self.latency:
            return ""
        lat = np.asarray(self.latency) * 1e3
        return (f"latency median {np.median(lat):.0f} ms, p99 {np.percentile(lat, 99):.0f} ms, "
                f"max {lat.max():.0f} ms")

    def summary(self) -> str:
        """One line: frames written and dropped, latency, why it ended."""
        which = "frame" if len(self.dropped) == 1 else "frames"
        drop = (f"{self.frames_dropped} dropped ({which} {_ranges(self.dropped)}; processing "
                f"was behind, {self.shots_dropped} shots)" if self.dropped else "0 dropped")
        part = f", {self.partial} partial frame not written" if self.partial else ""
        lat = self.latency_text()
        n = self.frames_written
        return (f"{n} frame{'' if n == 1 else 's'} written, {drop}{part}"
                f"{', ' + lat if lat else ''}; {self.shots} shots in {self.wall:.1f} s; "
                f"stream {self.ended}")


def _ranges(idx: list) -> str:
    """``3-5, 9`` of a sorted list of integers (the first 5 runs, then ``…``)."""
    runs: list = []
    for i in idx:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    text = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:5]]
    return ", ".join(text) + (", …" if len(runs) > 5 else "")


class _Admission:
    """Frame numbering of the source's shots and the bounded count of queued frames
    (shared by the two threads under one lock)."""

    def __init__(self, proc: FrameProcessor, max_queued: int):
        self.rate, self.n_shots = proc.frame_rate, proc.frame_shots
        self.max_queued = max(1, int(max_queued))
        self.cond = threading.Condition()
        self.queued = 0            # admitted frames none of whose shots processing took
        self.taken = -1            # frame index of the last piece processing took
        self.t0: float | None = None
        self.current = -1          # frame index of the last shot seen
        self.current_ok = False    # the current frame was admitted
        self.seen = 0              # shots seen (frame_shots numbering)
        self.admitted: collections.deque = collections.deque()
        self.dropped: set = set()
        self.complete_wall: dict = {}

    def split(self, times: np.ndarray):
        """``(frame index, slice)`` runs of a chunk's shot times."""
        if self.rate is not None:
            if self.t0 is None:
                self.t0 = float(times[0])
            i, a = max(self.current, 0), 0
            while a < times.size:
                end = self.t0 + (i + 1) / self.rate  # as FrameProcessor._window
                b = int(np.searchsorted(times, end, side="left"))
                if b > a:
                    yield i, slice(a, b)
                a, i = max(a, b), i + 1
            return
        a = 0
        while a < times.size:
            i = (self.seen + a) // self.n_shots
            b = min(times.size, (i + 1) * self.n_shots - self.seen)
            yield i, slice(a, b)
            a = b
        self.seen += times.size


@dataclass(frozen=True)
class _Piece:
    """A queue item: ``index`` of the frame, the chunk of its shots (None: end)."""

    index: int
    chunk: Recording | None


class LiveRun:
    """Frames of a live source, processed and written as they come (see the module doc).

    ``source`` : a :class:`~mems_stereo.io.live_sources.LiveSource`; ``processor`` : a
    :class:`FrameProcessor`; ``write`` : called with each finished :class:`Frame` in
    the caller's thread; ``max_queued`` : admitted frames not yet written (the bound of
    the queue); ``on_progress`` : called with the :class:`LiveStats` after each frame.
    """

    def __init__(self, source, processor: FrameProcessor, write: Callable[[Frame], object],
                 max_queued: int = 3, on_progress: Callable[[LiveStats], object] | None = None):
        self.source = source
        self.proc = processor
        self.write = write
        self.on_progress = on_progress
        self.adm = _Admission(processor, max_queued)
        self.stats = LiveStats()
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._t_start = 0.0

    def stop(self) -> None:
        """End the run cleanly (any thread, a signal handler too)."""
        self._stop.set()
        self.source.stop()

    # ------------------------------------------------------------ source thread
    def _admit(self, i: int) -> bool:
        """Decide on frame ``i`` when its first shot arrives (see the module doc)."""
        a = self.adm
        with a.cond:
            now = time.monotonic()
            for j in range(a.current, i):  # every frame before i is complete now
                a.complete_wall.setdefault(j, now)
            a.current = i
            if self.source.can_wait:
                while a.queued >= a.max_queued and not self._stop.is_set():
                    a.cond.wait(POLL)
            if a.queued >= a.max_queued and not self.source.can_wait:
                old = next(j for j in a.admitted if j > a.taken)  # the oldest waiting
                a.admitted.remove(old)
                a.dropped.add(old)
                a.queued -= 1
            ok = a.queued < a.max_queued and not self._stop.is_set()
            if ok:
                a.queued += 1
                a.admitted.append(i)
            else:
                a.dropped.add(i)
            a.current_ok = ok
            return ok

    def _produce(self) -> None:
        a = self.adm
        try:
            for chunk in self.source:
                t = np.asarray(chunk.shot_time)
                if not t.size:
                    continue
                for i, s in a.split(t):
                    ok = a.current_ok if i == a.current else self._admit(i)
                    if not ok:
                        with a.cond:
                            self.stats.shots_dropped += s.stop - s.start
                        continue
                    part = Recording(chunk.system, t[s], chunk.bins[s], chunk.zero_crossings,
                                     chunk.rising, {}, chunk.source)
                    self.q.put(_Piece(i, part))
                if self._stop.is_set():
                    break
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            self._error = e
        finally:
            with a.cond:
                now = time.monotonic()
                if not self._stop.is_set():  # the stream ended: its last frame is complete
                    a.complete_wall.setdefault(a.current, now)
            self.q.put(_Piece(-1, None))

    # ------------------------------------------------------------ caller's thread
    def run(self) -> LiveStats:
        """Run to the end of the stream (or :meth:`stop`); returns the statistics.

        An error of the source (a :class:`~mems_stereo.errors.FormatError`) is raised
        here after the frames before it were written.
        """
        self._t_start = time.monotonic()
        th = threading.Thread(target=self._produce, name="mems-stereo live source",
                              daemon=True)
        th.start()
        try:
            self._consume()
        finally:
            self.stop()
            th.join()
            self.stats.wall = time.monotonic() - self._t_start
            self.stats.dropped = sorted(self.adm.dropped)
            self.stats.ended = ("stopped" if self._stop_requested
                                else (self.source.ended or "finished"))
        if self._error is not None:
            raise self._error
        return self.stats

    _stop_requested = False

    def _consume(self) -> None:
        while True:
            try:
                piece = self.q.get(timeout=POLL_IN_FLIGHT if self.proc.in_flight else POLL)
            except queue.Empty:
                for f in self.proc.ready():  # frames from worker processes
                    self._emit(f)
                continue
            if piece.chunk is None:
                break
            with self.adm.cond:
                if piece.index in self.adm.dropped:  # made room for a newer frame
                    self.stats.shots_dropped += piece.chunk.n_shots
                    continue
                if piece.index != self.adm.taken:  # a frame's first shots: it leaves the queue
                    self.adm.taken = piece.index
                    self.adm.queued -= 1
                    self.adm.cond.notify_all()
            self.stats.shots += piece.chunk.n_shots
            for f in self.proc.push(piece.chunk):
                self._emit(f)
        self._stop_requested = self._stop.is_set()
        if self._error is not None:
            return
        for f in self.proc.flush():
            if self._stop_requested:
                g = self._mapped(f)
                with self.adm.cond:
                    complete = g is None or g.index in self.adm.complete_wall
                if not complete:  # stopped before its shots were all in: not written
                    self.stats.partial += 1
                    self._take(g)
                    continue
            self._emit(f)

    def _mapped(self, f: Frame) -> Frame | None:
        """``f`` with the source's frame index (frame_shots: the processor numbers the
        admitted frames only); None for a dropped frame."""
        a = self.adm
        with a.cond:
            if a.rate is None and a.admitted:
                f = dataclasses.replace(f, index=a.admitted[0])
            return None if f.index in a.dropped else f

    def _take(self, f: Frame) -> bool:
        """Mark ``f`` as out of the queue; True where it was an admitted frame."""
        a = self.adm
        with a.cond:
            mine = bool(a.admitted) and a.admitted[0] == f.index
            if mine:
                a.admitted.popleft()
            return mine

    def _emit(self, f: Frame) -> None:
        f = self._mapped(f)
        if f is None:
            return
        self.write(f)
        now = time.monotonic()
        # the frame's temporaries are freed: hand them back to the OS (milliseconds), so
        # the two threads' heaps do not creep up over a long run
        release_freed_memory()
        self._take(f)
        due = self.source.due(f.end)
        with self.adm.cond:
            cw = self.adm.complete_wall
            ref = due if due is not None else cw.get(f.index, now)
            for j in [j for j in cw if j <= f.index]:  # frames up to f are done with
                del cw[j]
        self.stats.frames_written += 1
        self.stats.latency.append(now - ref)
        self.stats.written_at.append(now - self._t_start)
        if self.on_progress is not None:
            self.on_progress(self.stats)
