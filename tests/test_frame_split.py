"""One frame on several cores (issue 31): a frame's pixels and peaks split across shares.

The split's three steps (:mod:`mems_stereo.pipeline.frame_split`) give the cloud and
counts of one process, byte for byte: run here one share after another, on room-light
frames (peaks in more than one fusion block) and floodlight frames (the matched filter
confirming candidates), and in worker processes
(:class:`~mems_stereo.pipeline.frame_workers.SplitFrameProcessor`) through a live run.
A worker's error is raised and the next frame is still right; a dead worker is reported.
"""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from conftest import assert_same_frames

from mems_stereo import data
from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.live_sources import ReplaySource
from mems_stereo.io.recording import read_recording
from mems_stereo.pipeline.frame_split import share_pixels, split_frame_cloud
from mems_stereo.pipeline.frame_workers import (
    SplitFrameProcessor,
    WorkerError,
    frame_processor,
)
from mems_stereo.pipeline.frames import (
    FrameProcessor,
    FrameShots,
    frame_cloud,
    iter_frames,
    recording_chunks,
)
from mems_stereo.pipeline.live_queue import LiveRun

ROOM = data.path("room.h5")
HZ = 200.0  # 8 frames of 100 shots in room.h5


class _Shots(FrameProcessor):
    """A frame processor that keeps each frame's shots instead of processing them."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.shots = []

    def _start(self, start, end, shots):
        self.shots.append(shots)
        self.frames_done += 1


def _frame_shots(name: str, hz: float | None, n: int, shots: int | None = None):
    rec = read_recording(data.path(name))
    p = _Shots(rec.system, frame_rate=hz, frame_shots=shots)
    for c in recording_chunks(rec, 1000):
        p.push(c)
    p.flush()
    return p, p.shots[:n]


def _assert_same_cloud(got, ref) -> None:
    """``(cloud, counts)`` pairs equal: counts, points and every attribute (dtype and
    bytes, NaN included), in the same order."""
    (ca, na), (cb, nb) = got, ref
    assert na == nb
    assert ca.points.tobytes() == cb.points.tobytes()
    assert list(ca.attributes) == list(cb.attributes)
    for k, v in cb.attributes.items():
        assert ca.attributes[k].dtype == v.dtype and ca.attributes[k].tobytes() == v.tobytes(), k


@pytest.mark.parametrize("name, hz", [("room.h5", 50.0), ("floodlight.h5", 50.0)])
def test_split_frames_are_one_process_byte_for_byte(name, hz):
    """Two frames of each recording split in 2 and 3 shares: the cloud and counts of
    ``frame_cloud``; the room frames have peaks in two fusion blocks, the floodlight
    frames candidates the matched filter confirms (more peaks than the first stage's)."""
    p, frames = _frame_shots(name, hz, 2)
    for shots in frames:
        ref = frame_cloud(p.system, shots, p.settings, p.table, "f")
        assert ref[1].peaks > 0 and ref[1].points > 0
        for n in (2, 3):
            _assert_same_cloud(split_frame_cloud(p.system, shots, p.settings, p.table, "f", n),
                               ref)
    if name == "room.h5":
        assert ref[1].peaks > 16  # two blocks of the first-photon groups (FP_BLOCK)


def test_split_frames_without_peaks_are_one_process_byte_for_byte():
    """Frames of 12 shots find no peak: the empty cloud (its attributes) and counts of
    ``frame_cloud``."""
    p, frames = _frame_shots("room.h5", None, 2, shots=12)
    for shots in frames:
        ref = frame_cloud(p.system, shots, p.settings, p.table, "f")
        assert ref[1].peaks == 0 and ref[1].raw > 0
        _assert_same_cloud(split_frame_cloud(p.system, shots, p.settings, p.table, "f", 2), ref)


def test_share_pixels_interleave_every_pixel_once():
    parts = share_pixels(10, 3)
    assert [p.tolist() for p in parts] == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]]
    assert [p.tolist() for p in share_pixels(2, 4)] == [[0], [1]]
    assert np.array_equal(np.sort(np.concatenate(share_pixels(192, 2))), np.arange(192))


def test_split_workers_give_the_frames_of_one_process_and_report_errors():
    """A replay at max speed through a processor splitting each frame across two worker
    processes: every frame written in order, as one process makes it (the temporal
    fusion included), both workers busy in the first two steps.  Then shots the workers refuse:
    their error reaches the caller and the next frame is still the one-process frame
    (the other worker's stale answer is skipped); a killed worker: WorkerError naming
    the frame, no hang."""
    ref = list(iter_frames(ROOM, frame_rate=HZ))
    p, (shots,) = _frame_shots("room.h5", HZ, 1)
    written = []
    with frame_processor(p.system, workers=2, split="pixels", frame_rate=HZ) as proc:
        assert isinstance(proc, SplitFrameProcessor) and proc.compiled
        st = LiveRun(ReplaySource(ROOM, None, chunk_shots=50), proc, written.append).run()
        assert proc.in_flight == 0
        assert np.all(proc.step_cpu[:2] > 0) and proc.join_cpu > 0  # (< 16 peaks: one block)
        assert st.dropped == [] and st.frames_written == len(ref) == 8
        assert_same_frames(written, ref)

        proc.fusion = None  # the frames below alone (age 1)
        bad = FrameShots(shots.times, shots.bins[:, :, :10], None, shots.zc, shots.rising)
        with pytest.raises(FormatError, match="shape"):
            proc._start(0.0, 0.005, bad)
        proc._start(0.0, 0.005, shots)
        (frame,) = proc.ready()
        ref0 = frame_cloud(p.system, shots, p.settings, p.table, "f")
        ref0[0].attributes["age"] = np.ones(len(ref0[0]), np.int32)
        _assert_same_cloud((frame.cloud, frame.counts), ref0)
        os.kill(proc.worker_pids[1], signal.SIGKILL)
        os.waitpid(proc.worker_pids[1], 0)
        with pytest.raises(WorkerError, match="ended before frame 10"):
            proc._start(0.0, 0.005, shots)
    assert proc.workers == 0  # closed
    with pytest.raises(OptionError, match="split"):
        frame_processor(p.system, workers=2, split="rows", frame_rate=HZ)
