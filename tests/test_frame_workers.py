"""Frames on several cores (issue 31): the frame stages in worker processes.

The frames of a :class:`ParallelFrameProcessor` are those of one process, array for
array (temporal fusion included), returned in order with at most one frame per worker in
flight; a live run through it writes the same frames; a worker that dies is reported,
never waited for forever; one worker or one core gives the one-process path.
"""

from __future__ import annotations

import os
import signal

import pytest
from conftest import assert_same_frames

from mems_stereo import data
from mems_stereo.cli import main
from mems_stereo.errors import OptionError
from mems_stereo.io.live_sources import ReplaySource
from mems_stereo.io.recording import read_recording
from mems_stereo.pipeline.frame_workers import (
    ParallelFrameProcessor,
    WorkerError,
    default_workers,
    frame_processor,
)
from mems_stereo.pipeline.frames import FrameProcessor, iter_frames, recording_chunks
from mems_stereo.pipeline.live_queue import LiveRun

ROOM = data.path("room.h5")
HZ = 200.0  # 8 frames of 100 shots in room.h5


@pytest.fixture(scope="module")
def room():
    return read_recording(ROOM)


@pytest.fixture(scope="module")
def reference():
    """The frames of room.h5 at 200 Hz made in this process."""
    return list(iter_frames(ROOM, frame_rate=HZ))


def test_workers_give_the_frames_of_one_process_in_order(room, reference):
    """Chunks of 60 shots pushed into two workers: the frames come back in order, at most
    two in flight, equal to the one-process frames (the fusion, sequential, included)."""
    assert len(reference) == 8 and max(len(f.cloud) for f in reference) > 0
    got, flight = [], []
    with frame_processor(room.system, workers=2, frame_rate=HZ) as proc:
        assert isinstance(proc, ParallelFrameProcessor) and proc.workers == 2
        assert proc.compiled  # the workers run the compiled kernels, as one process does
        for chunk in recording_chunks(room, 60):
            got += proc.push(chunk)
            flight.append(proc.in_flight)
            got += proc.ready()
        got += proc.flush()
        assert proc.in_flight == 0 and proc.worker_cpu > 0
    assert max(flight) == 2
    assert_same_frames(got, reference)
    assert any(f.cloud["age"].max() > 1 for f in got)  # fused over frames
    assert proc.workers == 0  # closed


def test_live_run_through_workers_writes_theassert_same_frames(room, reference):
    """A replay at max speed through two workers: every frame written, in order, as one
    process makes it; the latencies are those of the written frames."""
    written = []
    with frame_processor(room.system, workers=2, frame_rate=HZ) as proc:
        st = LiveRun(ReplaySource(ROOM, None, chunk_shots=50), proc, written.append).run()
    assert st.dropped == [] and st.frames_written == 8 == len(st.latency)
    assert_same_frames(written, reference)


def test_a_dead_worker_is_reported(room):
    """A worker killed mid-run: the frame it held raises WorkerError (no hang); closing
    twice is harmless and a closed processor refuses frames."""
    proc = ParallelFrameProcessor(room.system, workers=1, frame_shots=100)
    chunks = list(recording_chunks(room, 400))
    os.kill(proc.worker_pids[0], signal.SIGKILL)
    os.waitpid(proc.worker_pids[0], 0)
    with pytest.raises(WorkerError, match="ended before frame 0"):
        proc.push(chunks[0])
        proc.flush()
    proc.close()
    proc.close()
    with pytest.raises(WorkerError, match="closed"):
        proc.push(chunks[1])


def test_one_worker_is_the_one_process_path(room):
    proc = frame_processor(room.system, workers=1, frame_rate=HZ)
    assert type(proc) is FrameProcessor and proc.workers == 0
    with pytest.raises(OptionError, match="workers"):
        frame_processor(room.system, workers=0, frame_rate=HZ)
    cores = os.sched_getaffinity(0)
    assert default_workers() == min(len(cores), 4) >= 1
    try:  # a machine (or CI runner) with one core: the one-process path by default
        os.sched_setaffinity(0, {min(cores)})
        assert default_workers() == 1
        assert type(frame_processor(room.system, frame_rate=HZ)) is FrameProcessor
    finally:
        os.sched_setaffinity(0, cores)


def test_cli_workers_option_refused(tmp_path, capsys):
    """--workers 0: one line naming the option, exit 2, nothing written (the help's
    example runs --workers 2; the frames of workers are those of one process above)."""
    assert main(["live", "--replay", str(ROOM), "--frame-rate", "10", "--workers", "0",
                 "-o", f"{tmp_path}/x/"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--workers" in err[0]
    assert not (tmp_path / "x").exists()
