"""Frames: a cloud every 1/f seconds (or every N shots), as a lidar delivers them.

:class:`FrameProcessor` takes consecutive chunks of shots (:class:`Recording` objects, as
a file, a recording in memory or a live source yields them) and returns each frame as
soon as it is complete: the frame's shots are processed by
:func:`~mems_stereo.pipeline.run.process_recording` (one interval table shared by every
frame), each point gets the mean time ``t`` of the shots its detections came from, and
the temporal fusion (:mod:`mems_stereo.pipeline.temporal`) merges it with the pixel's
history while the two agree.  :func:`iter_frames` is the loop over it.

Frame boundaries.  ``frame_rate`` f: frame i holds the shots with time in
``[t0 + i/f, t0 + (i+1)/f)``, t0 the first shot's time (empty windows give frames with
an empty cloud).  ``frame_shots`` N: frame i holds shots ``i·N … (i+1)·N − 1``; its start
is its first shot's time, its end the start plus N shot periods.  A frame is finished
once a shot at or after its end plus one mechanical period has arrived (so the zero
crossings after its last shot are known); the zero crossings it is processed with are
those within one mechanical period of its window.  The frames are therefore the same,
bit for bit, whatever the chunking of the source.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.recording import Recording, iter_shot_chunks, read_header
from mems_stereo.model.system import System
from mems_stereo.pipeline.classify_kernel import compiled_blocks
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.frame_bias import every_bias_removed
from mems_stereo.pipeline.pass1 import Counts
from mems_stereo.pipeline.point_times_kernel import shot_time_sums
from mems_stereo.pipeline.run import (
    checked_header,
    process_recording,
    recording_angles,
    run_table,
)
from mems_stereo.pipeline.settings import Settings
from mems_stereo.pipeline.temporal import TemporalFusion

#: points per block when the shots behind each point are gathered (bounds the (K, n) mask)
TIME_BLOCK = 256


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame of points.

    index : 0-based frame number.  start, end : s, on the recording's clock (its shot
    times), the frame's window ``[start, end)``.  cloud :
    :class:`~mems_stereo.pipeline.cloud.PointCloud` with the attributes of
    :func:`~mems_stereo.pipeline.run.process_recording` plus ``t`` (float64 s, the mean
    time of the shots the point's detections came from) and ``age`` (int32, frames of
    history fused into the point, 1: this frame alone).  counts :
    :class:`~mems_stereo.pipeline.pass1.Counts` of the frame's shots.
    """

    index: int
    start: float
    end: float
    cloud: PointCloud
    counts: Counts

    def __repr__(self) -> str:
        return (f"<Frame {self.index}: {self.start:.4f}–{self.end:.4f} s, "
                f"{self.counts.shots} shots, {len(self.cloud)} points>")


@dataclass(frozen=True, slots=True)
class FrameShots:
    """The shots of one frame: times (k,) float64 s, bins (k, H, W) uint16, labels
    (k, H, W) uint8 truth or None; zc, rising: the zero crossings within one mechanical
    period of the frame's window."""

    times: np.ndarray
    bins: np.ndarray
    labels: np.ndarray | None
    zc: np.ndarray
    rising: np.ndarray


def checked_frame_rate(frame_rate, frame_shots):
    """``(frame_rate, frame_shots)`` checked: exactly one of a positive frame rate (Hz,
    float) and a positive number of shots (int); the other None.  Raises
    :class:`~mems_stereo.errors.OptionError`."""
    if (frame_rate is None) == (frame_shots is None):
        raise OptionError("expected exactly one of frame_rate (Hz) and frame_shots")
    if frame_rate is not None:
        f = float(frame_rate)
        if not (np.isfinite(f) and f > 0):
            raise OptionError(f"frame_rate: expected a positive number of Hz, found "
                              f"{frame_rate!r}")
        return f, None
    if isinstance(frame_shots, bool) or not isinstance(frame_shots, (int, np.integer)) \
            or frame_shots < 1:
        raise OptionError(f"frame_shots: expected a positive integer, found {frame_shots!r}")
    return None, int(frame_shots)


class FrameProcessor:
    """Frames from consecutive chunks of shots, pushed as they come.

    ``system`` : the :class:`System` to process with; exactly one of ``frame_rate``
    (Hz) and ``frame_shots``; ``settings`` : :class:`Settings`; ``fusion`` : fuse each
    pixel's points over frames (:class:`~mems_stereo.pipeline.temporal.TemporalFusion`),
    else every frame stands alone (``age`` 1).

    :meth:`push` a :class:`Recording` chunk (shot times increasing across chunks, its
    zero crossings those known up to its last shot; repeats are merged) and get the
    frames it completes; :meth:`flush` at the end of the stream for the rest.  The
    buffer holds about one frame of shots.  :meth:`ready` returns the frames finished
    between calls (none here; the worker processes of
    :class:`~mems_stereo.pipeline.frame_workers.ParallelFrameProcessor` finish frames
    meanwhile), :meth:`close` (or a ``with`` block) frees what the processor holds.
    """

    def __init__(self, system: System, *, frame_rate=None, frame_shots=None,
                 settings: Settings | None = None, fusion: bool = True):
        self.frame_rate, self.frame_shots = checked_frame_rate(frame_rate, frame_shots)
        load_kernels()
        self.system = system
        self.settings = Settings() if settings is None else settings
        # every row of the interval table now (tens of ms, kept in its disk cache): a
        # frame then never computes rows, nor sorts its steps to find the missing ones
        self.table = run_table(system, self.settings).fill_all()
        self.table.save_cache()
        self.fusion = (TemporalFusion(system.receiver.height, system.receiver.width,
                                      self.settings.confidence, system=system)
                       if fusion else None)
        self.margin = 1.0 / float(system.scanner.f_mech)
        self.frames_done = 0
        self._t0 = None
        self._shot0 = 0  # index (in the stream) of the first buffered shot
        self._times = np.zeros(0)
        self._bins = np.zeros((0, system.receiver.height, system.receiver.width), np.uint16)
        self._labels: np.ndarray | None = None
        self._zc = np.zeros(0)
        self._rising = np.zeros(0, np.uint8)
        self._source = "<chunks>"
        self._last_time: float | None = None
        self._done: list[Frame] = []  # finished frames not yet returned

    #: worker processes the frame stages run in (0: this process)
    workers = 0

    @property
    def in_flight(self) -> int:
        """Frames being processed elsewhere (a worker process); 0 here: a frame is
        processed when its shots are complete."""
        return 0

    def ready(self) -> list[Frame]:
        """The frames finished since the last call (oldest first) without waiting; here
        always those :meth:`push` or :meth:`flush` returned already (none)."""
        out, self._done = self._done, []
        return out

    def close(self) -> None:
        """Free what the processor holds besides its buffer (nothing here)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def pending_shots(self) -> int:
        """Shots buffered that no returned frame holds yet."""
        return int(self._times.size)

    def push(self, chunk: Recording) -> list[Frame]:
        """Add a chunk of shots; returns the frames it completes (oldest first)."""
        self._append(chunk)
        return self._finished(final=False)

    def flush(self) -> list[Frame]:
        """The frames left at the end of the stream (the last one may be short)."""
        return self._finished(final=True)

    def _append(self, chunk: Recording) -> None:
        if not isinstance(chunk, Recording):
            raise FormatError(f"expected chunks of shots (Recordings), found "
                              f"{type(chunk).__name__}", field="chunk")
        h, w = self._bins.shape[1:]
        bins = np.asarray(chunk.bins)
        t = np.asarray(chunk.shot_time, dtype=np.float64)
        if bins.ndim != 3 or bins.shape[1:] != (h, w) or bins.shape[0] != t.size:
            raise FormatError(f"expected bins (k, {h}, {w}) with k = {t.size} shot times, "
                              f"found {bins.shape}", chunk.source, "/shots/bins")
        last = self._times[-1] if self._times.size else self._last_time
        if t.size and (np.any(np.diff(t) <= 0) or (last is not None and t[0] <= last)):
            raise FormatError("expected chunks in shot order (strictly increasing times)",
                              chunk.source, "/shots/time")
        if self._t0 is None and t.size:
            self._t0 = float(t[0])
            self._source = chunk.source
        lab = chunk.truth.get("label") if chunk.truth else None
        if lab is None or (self._labels is None and self._times.size):
            self._labels = None  # truth counts only where every shot has its labels
        else:
            prev = self._labels if self._labels is not None else np.zeros((0, h, w), np.uint8)
            self._labels = np.concatenate([prev, np.asarray(lab, np.uint8)])
        self._times = np.concatenate([self._times, t])
        self._bins = np.concatenate([self._bins, bins.astype(np.uint16, copy=False)])
        zc = np.concatenate([self._zc, np.asarray(chunk.zero_crossings, np.float64)])
        ri = np.concatenate([self._rising, np.asarray(chunk.rising, np.uint8)])
        self._zc, keep = np.unique(zc, return_index=True)
        self._rising = ri[keep]
        if t.size:
            self._last_time = float(t[-1])

    def _window(self, i: int) -> tuple[float, float]:
        """``(start, end)`` of frame i, s (frame_shots: from the first buffered shot)."""
        if self.frame_rate is not None:
            return self._t0 + i / self.frame_rate, self._t0 + (i + 1) / self.frame_rate
        start = float(self._times[0])
        return start, start + self.frame_shots / float(self.system.laser.f_rep)

    def _finished(self, final: bool) -> list[Frame]:
        while self._t0 is not None:
            if not self._times.size and (final or self.frame_shots is not None):
                break
            start, end = self._window(self.frames_done)
            if self.frame_rate is not None:
                k = int(np.searchsorted(self._times, end, side="left"))
            else:
                k = min(self.frame_shots, self._times.size)
            edge = end if self.frame_rate is not None or k == 0 else self._times[k - 1]
            if not final and not (self._last_time is not None
                                  and self._last_time >= edge + self.margin
                                  and (self.frame_rate is not None or k == self.frame_shots)):
                break
            self._start(start, end, self._take(k, start, end))
        return self.ready()

    def _take(self, k: int, start: float, end: float) -> FrameShots:
        """The first ``k`` buffered shots as a frame's, removed from the buffer."""
        m = self.margin
        z = (self._zc >= start - m) & (self._zc <= max(end, self._times[k - 1] if k else end) + m)
        shots = FrameShots(self._times[:k], self._bins[:k],
                           None if self._labels is None else self._labels[:k],
                           self._zc[z], self._rising[z])
        self._times, self._bins = self._times[k:], self._bins[k:]
        if self._labels is not None:
            self._labels = self._labels[k:]
        nxt = min(end, float(self._times[0])) if self._times.size else end
        keep = self._zc >= nxt - m
        self._zc, self._rising = self._zc[keep], self._rising[keep]
        self._shot0 += k
        return shots

    def _start(self, start: float, end: float, shots: FrameShots) -> None:
        """Process the next frame's shots; here at once, into the finished frames."""
        index = self.frames_done
        self.frames_done += 1
        cloud, counts = frame_cloud(self.system, shots, self.settings, self.table,
                                    f"{self._source} frame {index}")
        self._done.append(self._assemble(index, start, end, cloud, counts))

    def _assemble(self, index: int, start: float, end: float, cloud: PointCloud,
                  counts: Counts) -> Frame:
        """Frame ``index`` from its frame stages' cloud: fused with each pixel's history
        (in frame order: the fusion is sequential)."""
        if self.fusion is not None and len(cloud):  # an empty window has no pixel to fuse
            cloud = self.fusion.update(cloud)
        else:
            cloud.attributes["age"] = np.ones(len(cloud), np.int32)
        return Frame(index, float(start), float(end), cloud, counts)


def load_kernels() -> bool:
    """Import numba (True where it is installed): frames come one after another for as
    long as the source runs, so the stages' compiled kernels
    (:func:`~mems_stereo.util.lazy_numba.compiled_if_loaded`: the same numbers as their
    NumPy forms) pay for their one load (numba's disk cache) from the second frame on."""
    try:
        import numba  # noqa: F401
    except ImportError:  # pragma: no cover - numba is a declared dependency
        return False
    return True


def _empty_cloud(n_shots: int, unknown: int) -> tuple[PointCloud, Counts]:
    cloud = PointCloud(np.zeros((0, 3)), {"t": np.zeros(0)})
    return cloud, Counts(n_shots, unknown, 0, 0, 0, 0, 0)


def is_empty_frame(shots: FrameShots) -> bool:
    """Whether a frame has nothing to process: no shot, or fewer than two zero crossings
    (no shot angle known): :func:`frame_cloud` gives its empty cloud at once."""
    return shots.times.size == 0 or shots.zc.size < 2


def frame_recording(system: System, shots: FrameShots, source: str) -> Recording:
    """A frame's shots as the :class:`Recording` its stages read (``/truth/label`` where
    the shots carry labels)."""
    truth = {} if shots.labels is None else {"label": shots.labels}
    return Recording(system, shots.times, shots.bins, shots.zc, shots.rising, truth, source)


@contextlib.contextmanager
def frame_stages() -> Iterator[None]:
    """Context of a frame's stages: the kernels the processor loaded for blocks of any
    size (:func:`~mems_stereo.pipeline.classify_kernel.compiled_blocks`), every mean-angle
    bias removed (:func:`~mems_stereo.pipeline.frame_bias.every_bias_removed`: the
    temporal fusion averages the frames' noise, not a bias they share)."""
    with compiled_blocks(), every_bias_removed():
        yield


def frame_cloud(system: System, shots: FrameShots, settings: Settings, table, source: str):
    """``(cloud, counts)`` of one frame's shots: :func:`process_recording` on them, each
    point with ``t`` (:func:`point_times`) and its scan-angle band (``step_lo``,
    ``step_hi``, int32: the steps of the interval table its peak counted)."""
    k = shots.times.size
    if is_empty_frame(shots):
        return _empty_cloud(k, k)
    with frame_stages():
        res = process_recording(frame_recording(system, shots, source), system, settings,
                                table=table)
    return stamped_cloud(system, shots, table, res.peaks, res.cloud, res.theta,
                         res.valid), res.counts


def stamped_cloud(system: System, shots: FrameShots, table, peaks, cloud: PointCloud,
                  theta=None, valid=None, peak_times=None) -> PointCloud:
    """``cloud`` (the points of ``peaks``, one per pixel at most) with each point's time
    ``t`` (:func:`point_times`) and its peak's band ``step_lo``, ``step_hi`` (int32);
    ``theta``, ``valid`` : (K,) the shots' angles (default: computed here from
    ``shots``, as the frame's run computes them); ``peak_times`` : (Q,) float64 s, the
    time of every peak's point where computed elsewhere (blocks of peaks: each point's
    time is its peak's alone)."""
    band = peak_of_points(peaks, cloud, system.receiver.width)
    if peak_times is not None:
        cloud.attributes["t"] = np.asarray(peak_times, np.float64)[band]
    else:
        if theta is None:
            header = checked_header(frame_recording(system, shots, ""), system)
            theta, valid = recording_angles(header, system)
        steps = table.rows(theta, valid)
        cloud.attributes["t"] = point_times(shots, steps, peaks, band, table)
    cloud.attributes["step_lo"] = peaks.step_lo[band].astype(np.int32)
    cloud.attributes["step_hi"] = peaks.step_hi[band].astype(np.int32)
    return cloud


def peak_of_points(peaks, cloud: PointCloud, width: int) -> np.ndarray:
    """(N,) int64: the peak of each point (one peak per pixel at most)."""
    pix = peaks.pixel(width)
    order = np.argsort(pix, kind="stable")
    want = cloud["row"].astype(np.int64) * width + cloud["pixel"].astype(np.int64)
    return order[np.searchsorted(pix[order], want)]


def point_times(shots: FrameShots, steps: np.ndarray, peaks, band: np.ndarray,
                table) -> np.ndarray:
    """(N,) float64 s: per point, the mean time of the shots whose detection in its pixel
    the pass 2 of its peak counted (code in the peak's window and in the classifier's
    accepted interval, shot in the peak's scan-angle band); the frame's mean shot time
    where none (cannot happen for a point with detections).  Where numba is imported
    (the frames' processor loads it) one compiled loop
    (:func:`~mems_stereo.pipeline.point_times_kernel.shot_time_sums`: the same means but
    for the order of the sums)."""
    t = shots.times
    out = np.full(band.size, float(t.mean()) if t.size else np.nan)
    w = table.system.receiver.width
    known = np.flatnonzero(steps >= 0)
    tk, sk = t[known] - t[0], steps[known]
    got = shot_time_sums(shots.bins, known, tk, sk, peaks, band, (table.lo, table.hi))
    if got is not None:
        sums, n = got
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, t[0] + sums / np.maximum(n, 1), out)
    for a in range(0, band.size, TIME_BLOCK):
        q = band[a:a + TIME_BLOCK]
        row, col = peaks.row[q], peaks.col[q]
        codes = shots.bins[known[:, None], row, col]  # (K, n)
        pix = row * w + col
        at = (sk[:, None], pix)  # (K, n) the table's accepted codes
        ok = ((codes >= peaks.code_lo[q]) & (codes <= peaks.code_hi[q])
              & (sk[:, None] >= peaks.step_lo[q]) & (sk[:, None] <= peaks.step_hi[q])
              & (codes >= table.lo[at]) & (codes <= table.hi[at]))
        n = ok.sum(axis=0)
        mean = (tk @ ok) / np.maximum(n, 1)
        out[a:a + q.size] = np.where(n > 0, t[0] + mean, out[a:a + q.size])
    return out


def recording_chunks(source, chunk_shots: int = 8192) -> Iterator[Recording]:
    """A path (FORMAT v1) or a :class:`Recording` as consecutive Recording chunks of at
    most ``chunk_shots`` shots, each with every zero crossing of the recording and its
    ``/truth/label`` chunk where there is one (memory: one chunk)."""
    if isinstance(source, (str, os.PathLike)):
        source = os.fspath(source)
    hdr = read_header(source)
    name = source.source if isinstance(source, Recording) else source
    for _first, times, bins, lab in iter_shot_chunks(source, chunk_shots, truth_labels=True):
        yield Recording(hdr.system, times, bins, hdr.zero_crossings, hdr.rising,
                        {} if lab is None else {"label": lab}, name)


def iter_frames(source, system: System | None = None, *, frame_rate=None, frame_shots=None,
                settings: Settings | None = None, fusion: bool = True,
                chunk_shots: int = 8192) -> Iterator[Frame]:
    """Yield the frames of a recording, one :class:`Frame` every 1/``frame_rate`` s (or
    every ``frame_shots`` shots), each point stamped with its time ``t`` and ``age``.

    ``source`` : a FORMAT v1 path, a :class:`Recording`, or an iterable of Recording
    chunks of one acquisition (a live source); ``system`` : the system to process with
    (default: the recording's); ``fusion`` : temporal fusion of each pixel's points
    (:mod:`mems_stereo.pipeline.temporal`); ``chunk_shots`` : shots read at a time from a
    path or Recording.  Memory stays about one frame of shots.

    Examples
    --------
    >>> frames = list(ms.iter_frames(ms.data.path("room.h5"), frame_rate=50))
    >>> [(f.index, round(f.start, 3), round(f.end, 3), f.counts.shots) for f in frames]
    [(0, 0.0, 0.02, 400), (1, 0.02, 0.04, 400)]
    >>> cloud = frames[1].cloud             # fused with frame 0 where they agree
    >>> sorted(set(cloud["age"].tolist())), bool(np.all(cloud["t"] < 0.04))
    ([1, 2], True)
    >>> alone = list(ms.iter_frames(ms.data.path("room.h5"), frame_rate=50, fusion=False))
    >>> bool(np.all((alone[1].cloud["t"] >= 0.02) & (alone[1].cloud["age"] == 1)))
    True
    """
    if isinstance(source, (Recording, str, bytes, os.PathLike)):
        chunks: Iterable = recording_chunks(source, chunk_shots)
    else:
        chunks = source
    proc = None
    for chunk in chunks:
        if proc is None:
            if not isinstance(chunk, Recording):
                raise FormatError(f"expected chunks of shots (Recordings), found "
                                  f"{type(chunk).__name__}", field="source")
            sysm = chunk.system if system is None else system
            proc = FrameProcessor(sysm, frame_rate=frame_rate, frame_shots=frame_shots,
                                  settings=settings, fusion=fusion)
        yield from proc.push(chunk)
    if proc is not None:
        yield from proc.flush()
