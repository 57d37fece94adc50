"""Live mode (issue 31): sources, the bounded frame queue, ``mems-stereo live``.

Frames of a live source are those of ``process --frame-rate`` (byte for byte through
the CLI, array for array through the sources); a slow consumer drops whole frames,
counted and listed; SIGINT ends a run with every finished frame written.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_same_frames

from mems_stereo import data
from mems_stereo.cli import main
from mems_stereo.errors import FormatError
from mems_stereo.io.live_h5 import GrowingH5Source, LiveRecordingWriter
from mems_stereo.io.live_sources import LiveSource, ReplaySource, parse_rate
from mems_stereo.io.recording import read_recording
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.frames import Frame, iter_frames
from mems_stereo.pipeline.live_queue import LiveRun
from mems_stereo.pipeline.pass1 import Counts

ROOM = data.path("room.h5")


@pytest.fixture(scope="module")
def room():
    return read_recording(ROOM)


@pytest.fixture(scope="module")
def reference():
    """The frames of room.h5 at 50 Hz as iter_frames makes them from the file."""
    return list(iter_frames(ROOM, frame_rate=50))


def _feed(rec, step: int, send) -> None:
    """Call ``send(times, bins, zc, rising)`` with the shots in steps of ``step`` and the
    zero crossings up to each step's last shot (as an acquisition knows them)."""
    zc, ri, zi = rec.zero_crossings, rec.rising, 0
    for a in range(0, rec.n_shots, step):
        t = rec.shot_time[a:a + step]
        zj = int(np.searchsorted(zc, t[-1], side="right"))
        send(t, rec.bins[a:a + step], zc[zi:zj], ri[zi:zj])
        zi = zj
    send(np.zeros(0), rec.bins[:0], zc[zi:], ri[zi:])


# ------------------------------------------------------------------ sources

def test_parse_rate():
    assert parse_rate("max") is None and parse_rate("1") == 1.0 and parse_rate("2.5") == 2.5
    for bad in ("0", "-1", "nan", "fast"):
        with pytest.raises(FormatError, match="--rate"):
            parse_rate(bad)


def test_paced_replay_follows_the_recording_clock(room):
    """At rate r each piece is handed on when its last shot is due: wall ≈ duration / r."""
    src = ReplaySource(ROOM, rate=0.1)
    t0 = time.monotonic()
    lag = []
    for c in src:
        lag.append(time.monotonic() - src.due(float(c.shot_time[-1])))
    wall = time.monotonic() - t0
    dur = float(room.shot_time[-1] - room.shot_time[0]) / 0.1
    # never early; the upper bounds leave room for a loaded 2-core machine
    assert dur <= wall < dur + 1.5
    assert min(lag) >= 0 and np.median(lag) < 0.25


def test_growing_h5_file_swmr(room, reference, tmp_path):
    """A writer thread appends shots and crossings (SWMR); the reader follows the file while
    it grows and its frames are those of the finished recording."""
    path = tmp_path / "growing.h5"
    started = threading.Event()

    def writer():
        with LiveRecordingWriter(path, room.system, chunk_shots=64) as w:
            started.set()

            def send(t, b, z, r):
                w.append(t, b, z, r)
                time.sleep(0.005)
            _feed(room, 50, send)

    th = threading.Thread(target=writer)
    th.start()
    started.wait(5)
    src = GrowingH5Source(path, idle_timeout=5)
    chunks = list(src)
    th.join()
    assert src.ended == "finished" and len(chunks) > 2
    assert sum(c.n_shots for c in chunks) == room.n_shots
    assert_same_frames(list(iter_frames(iter(chunks), frame_rate=50)), reference)
    # the finished file reads as an ordinary recording
    assert np.array_equal(read_recording(path).bins, room.bins)


def test_growing_h5_idle_timeout(room, tmp_path):
    """A writer that stops writing (without finishing) ends the stream after the idle time."""
    path = tmp_path / "stalled.h5"
    w = LiveRecordingWriter(path, room.system).__enter__()
    try:
        w.append(room.shot_time[:100], room.bins[:100], room.zero_crossings[:10],
                 room.rising[:10])
        src = GrowingH5Source(path, idle_timeout=0.3)
        t0 = time.monotonic()
        n = sum(c.n_shots for c in src)
        assert src.ended == "idle" and 0.3 <= time.monotonic() - t0 < 2
        assert n == 100
    finally:
        w.close()


def test_zmq_socket_on_loopback(room, reference):
    zmq = pytest.importorskip("zmq")
    from mems_stereo.io.live_zmq import ZmqSource, send_end, send_shots, send_system

    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 1000)
    port = push.bind_to_random_port("tcp://127.0.0.1")

    def sender():
        send_system(push, room.system)
        _feed(room, 64, lambda t, b, z, r: send_shots(push, t, b, z, r))
        send_end(push)

    th = threading.Thread(target=sender)
    th.start()
    src = ZmqSource(f"tcp://127.0.0.1:{port}", idle_timeout=5, context=ctx)
    chunks = list(src)
    th.join()
    assert src.ended == "finished"
    assert_same_frames(list(iter_frames(iter(chunks), frame_rate=50)), reference)
    # a message whose parts do not match its header is refused, not read
    th = threading.Thread(target=lambda: (send_system(push, room.system), push.send_multipart(
        [b'{"format": "mems-stereo/live", "version": 1, "type": "shots", "n_shots": 2}',
         np.zeros(2).tobytes(), b"\0" * 10, b"", b""])))
    th.start()
    src = ZmqSource(f"tcp://127.0.0.1:{port}", idle_timeout=5, context=ctx)
    with pytest.raises(FormatError, match="message 2.*bins.*768 bytes"):
        list(src)
    th.join()
    push.close()
    ctx.term()


# ------------------------------------------------------------------ the bounded queue

class _Source(LiveSource):
    """Chunks of 10 shots every ``pause`` s, frames of 100 shots (shots at 1 kHz)."""

    def __init__(self, system, n_shots: int, pause: float, can_wait: bool):
        super().__init__(system, "test")
        self.n, self.pause, self.can_wait = n_shots, pause, can_wait

    def chunks(self):
        h, w = self.system.receiver.height, self.system.receiver.width
        for a in range(0, self.n, 10):
            time.sleep(self.pause)
            if self.stopped:
                return
            t = (a + np.arange(10)) * 1e-3
            yield self.chunk(t, np.zeros((10, h, w), np.uint16), np.zeros(0), np.zeros(0))
        self.ended = "finished"


class _Processor:
    """Frames of 0.1 s from the shots pushed (a stand-in that counts them, no processing)."""

    frame_rate, frame_shots, in_flight = 10.0, None, 0

    def __init__(self):
        self.t, self.i = [], 0

    def _frames(self, upto: float):
        out = []
        while (self.i + 1) * 0.1 <= upto + 1e-9:
            n = sum(1 for t in self.t if self.i * 0.1 - 1e-9 <= t < (self.i + 1) * 0.1 - 1e-9)
            out.append(Frame(self.i, self.i * 0.1, (self.i + 1) * 0.1,
                             PointCloud(np.zeros((0, 3)), {}), Counts(n, 0, 0, 0, 0, 0, 0)))
            self.i += 1
        return out

    def push(self, chunk):
        self.t += chunk.shot_time.tolist()
        return self._frames(float(chunk.shot_time[-1]) - 1e-3)

    def flush(self):
        return self._frames(max(self.t) + 1e-3)

    def ready(self):
        return []


@pytest.mark.parametrize("can_wait", [False, True])
def test_slow_sink_drops_whole_frames_counted(room, can_wait):
    """Frames of 100 shots arrive every 0.02 s; the sink takes 0.1 s a frame.  A live source
    loses whole frames (never part of one), each counted and listed, the queue never above
    its bound; a source that can wait (replay at max) loses none."""
    written, queued = [], []
    src = _Source(room.system, 2000, 0.002, can_wait)

    def write(f):
        queued.append(run.adm.queued)
        written.append(f)
        time.sleep(0.1)
        # a live source outruns the sink on any machine, however loaded: the first write
        # lasts until the source has delivered every shot
        deadline = time.monotonic() + 20.0
        while not can_wait and len(written) == 1 and src.ended is None \
                and time.monotonic() < deadline:
            time.sleep(0.01)

    run = LiveRun(src, _Processor(), write, max_queued=2)
    st = run.run()
    n = len(written) + st.frames_dropped
    assert n == 20 and st.frames_written == len(written)
    assert sorted({f.index for f in written} | set(st.dropped)) == list(range(20))
    assert all(f.counts.shots == 100 for f in written)  # written frames are whole
    assert st.shots + st.shots_dropped == 2000 and st.shots_dropped == 100 * st.frames_dropped
    assert max(queued) <= 2
    if can_wait:
        assert st.dropped == [] and "0 dropped" in st.summary()
    else:
        assert st.frames_dropped >= 5
        assert f"{st.frames_dropped} dropped" in st.summary()


def test_drops_between_frames_with_the_real_processor(room):
    """A paced replay whose processing and sink are slower than its frames drops frames in the middle of
    the stream; the processor then sees windows without shots, and the run still ends with
    every admitted frame written whole (the frames after a gap as the shots make them)."""
    from mems_stereo.pipeline.frames import FrameProcessor

    src = ReplaySource(ROOM, rate=0.02)  # a frame every 0.25 s, processing is slower
    written = []

    def write(f):
        written.append(f)
        time.sleep(0.4)  # slower than the frames come, whatever the machine

    st = LiveRun(src, FrameProcessor(room.system, frame_rate=200), write, max_queued=1).run()
    assert st.frames_dropped > 0 and st.frames_written == len(written)
    assert max(f.index for f in written) > min(st.dropped)  # a frame written after a drop
    assert sorted({f.index for f in written} | set(st.dropped)) == list(range(8))
    assert all(f.counts.shots == 100 for f in written)


def test_stop_writes_finished_frames_only(room):
    """stop() mid-stream: the frames whose shots were complete are written, not the partial one."""
    written = []
    run = LiveRun(_Source(room.system, 2000, 0.002, True), _Processor(), written.append)
    threading.Timer(0.2, run.stop).start()
    st = run.run()
    assert st.ended == "stopped" and 0 < st.frames_written < 20
    assert all(f.counts.shots == 100 for f in written)
    assert [f.index for f in written] == list(range(len(written)))


# ------------------------------------------------------------------ the command

def test_live_replay_identical_to_process_frames(tmp_path):
    a, b = tmp_path / "live", tmp_path / "process"
    assert main(["live", "-q", "--replay", str(ROOM), "--rate", "max", "--frame-rate", "50",
                 "-o", f"{a}/"]) == 0
    assert main(["process", "-q", str(ROOM), "--frame-rate", "50", "-o", f"{b}/"]) == 0
    names = sorted(p.name for p in b.iterdir())
    assert names == ["room_000000.ply", "room_000001.ply"]
    assert sorted(p.name for p in a.iterdir()) == names
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


def test_live_refuses_bad_options(tmp_path, capsys):
    for argv, what in [([], "SOURCE"), (["--replay", str(ROOM), "-o", f"{tmp_path}/"],
                                        "--frame-rate"),
                       (["--replay", str(ROOM), "--frame-rate", "10"], "--output"),
                       (["--replay", str(ROOM), "--rate", "0", "--frame-rate", "10",
                         "-o", f"{tmp_path}/x/"], "--rate")]:
        assert main(["live", *argv]) == 2
        err = capsys.readouterr().err
        assert what in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_sigint_ends_cleanly_with_finished_frames(tmp_path):
    out = tmp_path / "frames"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-c", "from mems_stereo.cli import main; main()",
                          "live", "--replay", str(ROOM), "--rate", "0.003", "--frame-rate", "200",
                          "--queue-frames", "1",
                          "-o", f"{out}/"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not (out.is_dir() and any(out.glob("*.ply"))):
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=30)
    assert p.returncode == 0, stderr
    assert "stopped by SIGINT" in stdout and " written" in stdout, stdout
    files = sorted(out.iterdir())
    assert files and all(f.suffix == ".ply" and not f.name.startswith(".") for f in files)
    n = int(stdout.split(" frame")[0].rsplit(" ", 1)[-1])
    assert len(files) == n < 8
    from mems_stereo.viz.export import read_cloud

    for f in files:
        read_cloud(f)  # complete files only


# ------------------------------------------------------------------ viewers

def test_browser_viewer_sends_a_frame_to_a_websocket_client(reference):
    """The Foxglove WebSocket server advertises /mems_stereo/points and sends a subscribed
    client each frame (a client on loopback speaking the Foxglove protocol)."""
    pytest.importorskip("foxglove")
    import asyncio
    import json
    import struct

    from mems_stereo.viz.live_viewer import FIELDS, FoxgloveViewer
    from tornado.httpclient import HTTPRequest
    from tornado.websocket import websocket_connect

    v = FoxgloveViewer(port=0)

    async def client():
        ws = await websocket_connect(HTTPRequest(v.url), subprotocols=["foxglove.sdk.v1"])
        chans = []
        while not chans:
            m = json.loads(await asyncio.wait_for(ws.read_message(), 5))
            chans = m.get("channels", []) if m.get("op") == "advertise" else []
        assert chans[0]["topic"] == "/mems_stereo/points"
        assert chans[0]["schemaName"] == "foxglove.PointCloud"
        await ws.write_message(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 7, "channelId": chans[0]["id"]}]}))
        await asyncio.sleep(0.3)
        v.write(reference[1])
        m = await asyncio.wait_for(ws.read_message(), 5)
        ws.close()
        return m

    try:
        m = asyncio.run(client())
    finally:
        v.close()
    op, sub, stamp = struct.unpack_from("<BIQ", m)
    assert (op, sub, stamp) == (1, 7, round(reference[1].start * 1e9))
    stride = sum(np.dtype(dt).itemsize for _, dt, _ in FIELDS)
    assert len(m) > len(reference[1].cloud) * stride  # the packed points and their fields


@pytest.mark.render
def test_open3d_viewer_headless(reference):
    from mems_stereo.viz.live_viewer import Open3DViewer
    from mems_stereo.viz.render import render_available

    ok, why = render_available()
    if not ok:
        pytest.skip(f"headless OpenGL unavailable: {why}")
    v = Open3DViewer(visible=False)
    try:
        for f in reference:
            v.write(f)
        img = np.asarray(v.vis.capture_screen_float_buffer(True))
        assert len(v.pcd.points) == len(reference[-1].cloud)
        assert (img < 0.99).any(axis=2).sum() >= len(reference[-1].cloud)  # points drawn
    finally:
        v.close()


def test_ptu_file_being_written(tmp_path):
    """A T2 PTU file written record block by block (a partial record at every step) is
    followed; its shots are those `mems-stereo import` makes of the finished file."""
    from mems_stereo.io.live_ptu import PtuTailSource
    from mems_stereo.io.ptu import ptu_stream
    from mems_stereo.io.tttr import events_to_recording
    from mems_stereo.io.tttr_map import load_map

    ptu = data.path("room48.ptu")
    m = load_map(data.path("room48_map.json"))
    info, blocks = ptu_stream(ptu)
    events_to_recording(blocks, info, m, m.system, tmp_path / "ref.h5")
    ref = read_recording(tmp_path / "ref.h5")
    raw = Path(ptu).read_bytes()
    path = tmp_path / "growing.ptu"
    path.write_bytes(raw[:752])  # the header (its record offset)
    started = threading.Event()

    def writer():
        with open(path, "ab") as f:
            started.set()
            for a in range(752, len(raw), 4001):  # 4001: records cut in the middle
                f.write(raw[a:a + 4001])
                f.flush()
                time.sleep(0.002)

    th = threading.Thread(target=writer)
    th.start()
    started.wait(5)
    src = PtuTailSource(path, m, m.system, idle_timeout=3, block_records=500)
    chunks = list(src)
    th.join()
    assert src.ended == "finished" and len(chunks) > 5
    assert np.array_equal(np.concatenate([c.shot_time for c in chunks]), ref.shot_time)
    assert np.array_equal(np.concatenate([c.bins for c in chunks]), ref.bins)
    zc = np.unique(np.concatenate([c.zero_crossings for c in chunks]))
    assert np.array_equal(zc, ref.zero_crossings)


def test_live_growing_file_through_the_command(room, tmp_path):
    """``mems-stereo live REC.h5``: a recording written by the live writer (here finished
    before the run) gives the frames ``process --frame-rate`` gives of the same shots."""
    rec = tmp_path / "acq.h5"
    with LiveRecordingWriter(rec, room.system) as w:
        _feed(room, 200, w.append)
    a, b = tmp_path / "live", tmp_path / "process"
    assert main(["live", "-q", str(rec), "--frame-rate", "50", "-o", f"{a}/"]) == 0
    assert main(["process", "-q", str(ROOM), "--frame-rate", "50", "-o", f"{b}/"]) == 0
    assert sorted(p.name for p in a.iterdir()) == ["acq_000000.ply", "acq_000001.ply"]
    for i in range(2):
        assert (a / f"acq_{i:06d}.ply").read_bytes() == (b / f"room_{i:06d}.ply").read_bytes()


# ------------------------------------------------------------------ torn ends

def test_growing_h5_unpublished_append_reported_not_read(room, tmp_path):
    """Shots a writer appended but never published in /live/state (it stopped between
    the two) are not read; the idle end says how many were left."""
    import h5py

    path = tmp_path / "acq.h5"
    with LiveRecordingWriter(path, room.system) as w:
        _feed(room, 200, w.append)
    with h5py.File(path, "r+") as f:  # as if the last 50 shots were never published
        f["/live/state"][...] = [room.n_shots - 50, room.zero_crossings.size, 0]
    src = GrowingH5Source(path, idle_timeout=0.3)
    got = np.concatenate([c.shot_time for c in src])
    assert np.array_equal(got, room.shot_time[:-50])
    assert src.ended.startswith("idle (50 shots, 0 zero crossings past"), src.ended


def test_ptu_torn_last_record_reported_not_read(tmp_path):
    """A PTU file whose writer stopped inside a record: the whole records are read, the
    torn one is not, and the idle end says so (and how many of the header's records)."""
    from mems_stereo.io.live_ptu import PtuTailSource
    from mems_stereo.io.ptu import read_ptu_header
    from mems_stereo.io.tttr_map import load_map

    src_path = data.path("room48.ptu")
    m = load_map(data.path("room48_map.json"))
    raw = Path(src_path).read_bytes()
    hdr = read_ptu_header(src_path)
    off = len(raw) - 4 * hdr.n_records
    k = hdr.n_records // 2
    whole, torn = tmp_path / "whole.ptu", tmp_path / "torn.ptu"
    whole.write_bytes(raw[:off + 4 * k])
    torn.write_bytes(raw[:off + 4 * k + 3])
    a = list(PtuTailSource(whole, m, m.system, idle_timeout=0.2))
    src = PtuTailSource(torn, m, m.system, idle_timeout=0.2)
    b = list(src)
    assert np.array_equal(np.concatenate([c.bins for c in a]), np.concatenate([c.bins for c in b]))
    assert src.ended == (f"idle ({k} of the header's {hdr.n_records} records written; a torn "
                         "last record (3 bytes) left unread)")


def test_zmq_socket_through_the_command(room, tmp_path, capsys):
    """``mems-stereo live tcp://…``: frames named ``live_<index>``; a malformed message in
    the middle of a stream ends the command with one line, exit 2, and no bag."""
    zmq = pytest.importorskip("zmq")
    from mems_stereo.io.live_zmq import send_end, send_shots, send_system

    ctx = zmq.Context()

    def run(feed, out: str) -> int:
        push = ctx.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 1000)
        port = push.bind_to_random_port("tcp://127.0.0.1")
        th = threading.Thread(target=feed, args=(push,))
        th.start()
        try:
            return main(["live", "-q", f"tcp://127.0.0.1:{port}", "--frame-rate", "50",
                         "--idle-timeout", "5", "-o", out])
        finally:
            th.join()
            push.close()

    def whole(push):
        send_system(push, room.system)
        _feed(room, 200, lambda t, b, z, r: send_shots(push, t, b, z, r))
        send_end(push)

    def torn(push):
        send_system(push, room.system)
        k, zc = 600, room.zero_crossings
        z = zc <= room.shot_time[k - 1]
        send_shots(push, room.shot_time[:k], room.bins[:k], zc[z], room.rising[z])
        push.send_multipart([b'{"format": "mems-stereo/live", "version": 1, "type": "shots", '
                             b'"n_shots": 2}', np.zeros(2).tobytes(), b"\0" * 10, b"", b""])

    try:
        assert run(whole, f"{tmp_path}/frames/") == 0
        assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [
            "live_000000.ply", "live_000001.ply"]
        capsys.readouterr()
        assert run(torn, str(tmp_path / "bag.mcap")) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "message 3: bins" in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]
    finally:
        ctx.term()
