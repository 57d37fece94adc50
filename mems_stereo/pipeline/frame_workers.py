"""Frames on several cores: the frame stages of consecutive frames in worker processes.

A frame's stages (:func:`~mems_stereo.pipeline.frames.frame_cloud`: pass 1, the peak
search, the matched filter, the fusion of its peaks) depend on its own shots only; the
temporal fusion (:class:`~mems_stereo.pipeline.temporal.TemporalFusion`) depends on every
frame before it.  :class:`ParallelFrameProcessor` therefore sends frame i's shots to
worker ``i mod n`` (a process of its own: the stages are NumPy and numba code holding
the GIL for much of their time) and applies the temporal fusion in the calling process,
in frame order, as the workers' clouds come back.  The frames are the same, bit for bit,
as :class:`~mems_stereo.pipeline.frames.FrameProcessor`'s (the same code on the same
inputs); n frames are processed at once, so the throughput is up to n times one
process's, while a frame's latency stays its own processing time.

:class:`SplitFrameProcessor` (``split="pixels"``) instead sends every frame to every
worker, each computing its share of the frame's pixels and peaks
(:mod:`mems_stereo.pipeline.frame_split`: three steps, the small joins between them
here): a frame's latency is about its CPU time over n plus the joins, one frame at a
time (the throughput of one frame's latency).  Its frames are those of one process too.

At most ``n`` frames are in flight: :meth:`~ParallelFrameProcessor.push` waits for the
oldest when a frame completes while every worker is busy (so a live run's bounded
queue, :mod:`mems_stereo.pipeline.live_queue`, fills and drops as with one process:
never an unbounded backlog).  Each worker fills the interval table and processes a
synthetic frame (:func:`~mems_stereo.pipeline.live_warmup.synthetic_shots`) before the
processor returns, so the compiled kernels are loaded before the first real frame (a
few seconds).  The workers run in a session of their own and ignore SIGINT: a Ctrl-C
reaches the caller only, which stops the run, and the frames in flight finish and are
returned by :meth:`~ParallelFrameProcessor.flush`.  A worker ends when the caller closes
the processor or ends.
"""

from __future__ import annotations

import collections
import os
import signal
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection

import numpy as np

from mems_stereo.errors import MemsStereoError, OptionError
from mems_stereo.model.system import System
from mems_stereo.pipeline.frame_split import (
    frame_of_means,
    fusion_blocks,
    joined_peaks,
    share_means,
    share_peaks,
    share_pixels,
    share_scores,
    supported_blocks,
)
from mems_stereo.pipeline.frames import (
    Frame,
    FrameProcessor,
    FrameShots,
    frame_cloud,
    frame_stages,
    is_empty_frame,
    load_kernels,
)
from mems_stereo.pipeline.live_warmup import synthetic_shots
from mems_stereo.pipeline.run import run_table
from mems_stereo.util.memory import release_freed_memory

#: the most worker processes the default (:func:`default_workers`) starts
MAX_DEFAULT_WORKERS = 4
#: seconds a worker may take to start (imports, interval table, warm-up frame)
START_TIMEOUT = 300.0
#: how the frames go to the workers (:func:`frame_processor`): whole frames, frame i to
#: worker i mod n, or every frame's pixels across all workers
SPLITS = ("frames", "pixels")


class WorkerError(MemsStereoError, RuntimeError):
    """A frame worker process ended or failed without its frame (or the processor was
    closed)."""


def available_cores() -> int:
    """CPU cores this process may run on (``os.sched_getaffinity``; ``os.cpu_count``
    where the platform has no affinity)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def default_workers() -> int:
    """Worker processes by default: one per available core, at most
    :data:`MAX_DEFAULT_WORKERS`; 1 (no worker: the frames in the calling process) on a
    single core."""
    return max(1, min(available_cores(), MAX_DEFAULT_WORKERS))


def frame_processor(system: System, *, workers: int | None = None, split: str = "frames",
                    **kw) -> FrameProcessor:
    """A :class:`FrameProcessor` (``workers`` 1, or None on one core) or, with
    ``workers`` processes (None: :func:`default_workers`), a
    :class:`ParallelFrameProcessor` (``split`` "frames": the most frames per second) or
    a :class:`SplitFrameProcessor` ("pixels": the lowest latency per frame); ``kw`` as
    :class:`FrameProcessor`'s.  Close it when done (``with`` block or
    :meth:`~FrameProcessor.close`)."""
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise OptionError(f"workers: expected a positive integer, found {workers!r}")
    if split not in SPLITS:
        raise OptionError(f"split: expected one of {', '.join(SPLITS)}, found {split!r}")
    if n == 1:
        return FrameProcessor(system, **kw)
    cls = SplitFrameProcessor if split == "pixels" else ParallelFrameProcessor
    return cls(system, workers=n, **kw)


def start_worker() -> tuple[subprocess.Popen, Connection]:
    """A worker process (``python -m mems_stereo.pipeline.frame_workers FD``: the calling
    interpreter with its ``sys.path``, no re-import of the caller's main script; a session
    of its own: a Ctrl-C on the terminal reaches the caller only) and the
    :class:`~multiprocessing.connection.Connection` to it (a socket pair)."""
    mine, theirs = socket.socketpair()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    try:
        proc = subprocess.Popen([sys.executable, "-m", __name__, str(theirs.fileno())],
                                pass_fds=(theirs.fileno(),), env=env,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    finally:
        theirs.close()
    return proc, Connection(mine.detach())


def worker_main(fd: int) -> None:
    """A worker process on the connection ``fd``: ``(system, settings)``, then the table
    and a warm-up frame (answered ``("ready", -1, s, compiled)``: seconds, whether the
    compiled kernels are loaded), then ``(index, FrameShots,
    source)`` jobs answered with ``("ok", index, cloud, counts, cpu s)`` (or ``("error",
    index, exception)``) until None or the end of the connection."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    conn = Connection(fd)
    load_kernels()  # the stages' compiled kernels run only where numba is imported
    try:
        system, settings = conn.recv()
        table = run_table(system, settings).fill_all()
        t0 = time.perf_counter()
        frame_cloud(system, synthetic_shots(system), settings, table, "warm-up")
        conn.send(("ready", -1, time.perf_counter() - t0, "numba" in sys.modules))
    except BaseException as e:  # noqa: BLE001 - handed to the parent
        conn.send(("error", -1, e))
        return
    held: dict = {}  # the split frame's share between its steps
    try:
        while (job := conn.recv()) is not None:
            if job[0] == "split":
                _answer_split(conn, system, settings, table, job, held)
                continue
            index, shots, source = job
            c0 = time.process_time()
            try:
                cloud, counts = frame_cloud(system, shots, settings, table, source)
            except Exception as e:  # noqa: BLE001 - handed to the parent
                conn.send(("error", index, e))
                continue
            conn.send(("ok", index, cloud, counts, time.process_time() - c0))
            del cloud, counts, shots
            release_freed_memory()  # the frame's temporaries back to the OS: a flat heap
    except (EOFError, OSError):  # the parent ended
        return


def _answer_split(conn: Connection, system, settings, table, job, held: dict) -> None:
    """Run a split job and send its answer (or the exception) on ``conn``."""
    index = job[1]
    c0 = time.process_time()
    try:
        answer = split_step(system, settings, table, job, held)
    except Exception as e:  # noqa: BLE001 - handed to the parent
        held.clear()
        conn.send(("error", index, e))
        return
    conn.send(("ok", index, answer, time.process_time() - c0))
    if job[2] == "means":
        release_freed_memory()  # the frame's temporaries back to the OS: a flat heap


def split_step(system: System, settings, table, job, held: dict):
    """One step of a worker's share of a frame (:mod:`~mems_stereo.pipeline.frame_split`),
    ``job`` = ``("split", index, step, payload)``: "scores" (payload ``(shots, source,
    pixels)``: the share's flat pixels), "peaks" (payload: the share's support) or "means"
    (payload: the share's block of peaks); ``held`` keeps the share's frame between
    steps.  Returns the step's answer."""
    _, _index, step, payload = job
    with frame_stages():
        if step == "scores":
            held.clear()
            held["frame"], answer = share_scores(system, payload[0], settings, table,
                                                 payload[1], payload[2])
            return answer
        if step == "peaks":
            return share_peaks(held["frame"], payload)
        return share_means(held.pop("frame"), payload)


class ParallelFrameProcessor(FrameProcessor):
    """A :class:`FrameProcessor` whose frame stages run in ``workers`` processes (see the
    module doc); the same frames.  ``compiled`` : every worker runs the stages' compiled
    kernels.  ``warm_up`` : seconds the slowest worker took for its
    synthetic frame; ``worker_cpu`` : CPU s the workers spent on real frames."""

    def __init__(self, system: System, *, workers: int = 2, **kw):
        super().__init__(system, **kw)
        self.worker_cpu = 0.0
        self._conns, self._procs = [], []
        self._pending: collections.deque = collections.deque()  # (index, start, end, conn)
        try:
            for _ in range(int(workers)):
                p, conn = start_worker()
                self._procs.append(p)
                self._conns.append(conn)
                conn.send((system, self.settings))
            answers = [self._receive(c, -1, START_TIMEOUT) for c in self._conns]
            self.warm_up = max(a[0] for a in answers)
            self.compiled = all(a[1] for a in answers)
        except BaseException:
            self.close()
            raise

    @property
    def workers(self) -> int:
        """Worker processes running."""
        return len(self._conns)

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the workers."""
        return [p.pid for p in self._procs]

    @property
    def in_flight(self) -> int:
        """Frames sent to a worker and not yet returned."""
        return len(self._pending)

    def _receive(self, conn, index: int, timeout: float | None = None):
        """The answer of ``conn`` for job ``index``: ``(seconds,)`` or ``(cloud, counts,
        cpu)``; raises the worker's exception or :class:`WorkerError`."""
        try:
            if timeout is not None and not conn.poll(timeout):
                raise WorkerError(f"a frame worker did not start within {timeout:.0f} s")
            msg = conn.recv()
        except (EOFError, OSError) as e:
            raise WorkerError(f"a frame worker process ended before frame {index} "
                              f"({type(e).__name__})") from None
        if 0 <= msg[1] < index:  # a split frame's answer left by an error: read on
            return self._receive(conn, index, timeout)
        if msg[0] == "error":
            raise msg[2]
        if msg[1] != index:  # pragma: no cover - the protocol keeps order per worker
            raise WorkerError(f"frame worker answered frame {msg[1]}, expected {index}")
        return msg[2:]

    def _start(self, start: float, end: float, shots: FrameShots) -> None:
        """Send the next frame to its worker, after the oldest frame in flight came back
        where every worker is busy."""
        if not self._conns:
            raise WorkerError("the frame processor is closed")
        while len(self._pending) >= len(self._conns):
            self._collect_head()
        index = self.frames_done
        self.frames_done += 1
        conn = self._conns[index % len(self._conns)]
        try:
            conn.send((index, shots, f"{self._source} frame {index}"))
        except OSError:
            raise WorkerError(f"a frame worker process ended before frame {index}") from None
        self._pending.append((index, start, end, conn))

    def _collect_head(self) -> None:
        index, start, end, conn = self._pending.popleft()
        cloud, counts, cpu = self._receive(conn, index)
        self.worker_cpu += cpu
        self._done.append(self._assemble(index, start, end, cloud, counts))

    def ready(self) -> list[Frame]:
        """The frames finished since the last call, oldest first, without waiting (a
        frame whose predecessor is still in flight waits for it)."""
        while self._pending and self._pending[0][3].poll():
            self._collect_head()
        return super().ready()

    def flush(self) -> list[Frame]:
        """The frames left at the end of the stream, every frame in flight included."""
        out = super().flush()
        while self._pending:
            self._collect_head()
        return out + super().ready()

    def close(self) -> None:
        """Stop the workers (frames in flight are lost: :meth:`flush` first)."""
        for c in self._conns:
            try:
                c.send(None)
            except OSError:
                pass
        for p in self._procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for c in self._conns:
            c.close()
        self._conns, self._procs = [], []
        self._pending.clear()

    def __del__(self):  # a processor dropped without close: no orphan workers
        if getattr(self, "_procs", None):
            try:
                self.close()
            except Exception:  # noqa: BLE001 - interpreter shutdown: the workers see EOF
                pass


class SplitFrameProcessor(ParallelFrameProcessor):
    """A :class:`FrameProcessor` each of whose frames is split across ``workers``
    processes (:mod:`~mems_stereo.pipeline.frame_split`; the module doc): a frame is
    finished when :meth:`push` (or :meth:`flush`) returns it, as with one process
    (``in_flight`` 0), in about its CPU time over the workers plus the joins here; the
    same frames.  ``step_cpu`` : (3, workers) CPU s each worker spent in each step on
    real frames; ``join_cpu`` : CPU s this thread spent on the joins between them.  The
    start splits a synthetic frame once (``warm_up`` includes it), so that this process's
    part is loaded before the first real frame too."""

    def __init__(self, system: System, *, workers: int = 2, **kw):
        super().__init__(system, workers=workers, **kw)
        try:  # the joins' kernels loaded here too: the synthetic frame split once
            t0 = time.perf_counter()
            self.step_cpu, self.join_cpu = np.zeros((3, self.workers)), 0.0
            self._split(-1, synthetic_shots(system), "warm-up")
            self.warm_up += time.perf_counter() - t0
        except BaseException:
            self.close()
            raise
        self.step_cpu = np.zeros((3, self.workers))
        self.join_cpu = 0.0

    @property
    def in_flight(self) -> int:
        """0: a frame is processed when its shots are complete."""
        return 0

    @property
    def share_cpu(self) -> np.ndarray:
        """(workers,) CPU s each worker spent on real frames (``step_cpu`` summed)."""
        return self.step_cpu.sum(axis=0)

    def _start(self, start: float, end: float, shots: FrameShots) -> None:
        """Process the next frame across the workers, into the finished frames."""
        if not self._conns:
            raise WorkerError("the frame processor is closed")
        index = self.frames_done
        self.frames_done += 1
        source = f"{self._source} frame {index}"
        if is_empty_frame(shots):
            cloud, counts = frame_cloud(self.system, shots, self.settings, self.table, source)
        else:
            cloud, counts = self._split(index, shots, source)
        self._done.append(self._assemble(index, start, end, cloud, counts))

    def _split(self, index: int, shots: FrameShots, source: str):
        """``(cloud, counts)`` of frame ``index`` by the three steps of its shares."""
        sysm, st = self.system, self.settings
        W = sysm.receiver.width
        pixels = share_pixels(sysm.receiver.height * W, self.workers)
        conns = self._conns[:len(pixels)]
        self._ask(index, "scores", conns, [(shots, source, p) for p in pixels])
        sup, _ = self._answers(index, conns, 0)
        c0 = time.thread_time()
        with frame_stages():
            keeps = supported_blocks(sup, pixels, W)
        self.join_cpu += time.thread_time() - c0
        self._ask(index, "peaks", conns, keeps)
        parts, _ = self._answers(index, conns, 1)
        c0 = time.thread_time()
        with frame_stages():
            peaks = joined_peaks(sysm, parts, self.table, sup[0].n_per_step, st)
            blocks = fusion_blocks(peaks, len(conns))
        self.join_cpu += time.thread_time() - c0
        self._ask(index, "means", conns[:len(blocks)],
                  [peaks.take(slice(a, b)) for a, b in blocks])
        means, _ = self._answers(index, conns[:len(blocks)], 2)
        c0 = time.thread_time()
        with frame_stages():
            out = frame_of_means(sysm, shots, self.table, peaks, means, sup[0], st)
        self.join_cpu += time.thread_time() - c0
        return out

    def _ask(self, index: int, step: str, conns, payloads) -> None:
        """Send step ``step`` of frame ``index`` to each of ``conns`` with its payload."""
        for conn, payload in zip(conns, payloads):
            try:
                conn.send(("split", index, step, payload))
            except OSError:
                raise WorkerError(f"a frame worker process ended before frame "
                                  f"{index}") from None

    def _answers(self, index: int, conns, step: int) -> tuple[list, float]:
        """The answers of ``conns`` for step ``step`` (0, 1, 2) of frame ``index``, in
        order, and the CPU s they took in all (counted in ``step_cpu``)."""
        out, total = [], 0.0
        for i, conn in enumerate(conns):
            answer, cpu = self._receive(conn, index)
            self.step_cpu[step, i] += cpu
            total += cpu
            out.append(answer)
        self.worker_cpu += total
        return out, total


if __name__ == "__main__":
    worker_main(int(sys.argv[1]))
