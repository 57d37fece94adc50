"""Frames (mems_stereo.pipeline.frames, process --frame-rate/--frame-shots): windows, the
per-point time, independence of the chunking, the incremental processor, the sinks."""

from __future__ import annotations

import numpy as np
import pytest
from mems_stereo.viz.export import read_cloud
from mems_stereo.viz.export_frames import frame_path, read_frames_bag

import mems_stereo as ms
from mems_stereo.cli import main
from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.recording import Recording
from mems_stereo.pipeline.frames import FrameProcessor, iter_frames, recording_chunks

ROOM = str(ms.data.path("room.h5"))


@pytest.fixture(scope="module")
def rec():
    return ms.read_recording(ROOM)


@pytest.fixture(scope="module")
def frames():
    return list(iter_frames(ROOM, frame_rate=50))


def same_clouds(a, b, exact_points=True):
    assert len(a) == len(b) and sorted(a.attributes) == sorted(b.attributes)
    if exact_points:
        assert np.array_equal(a.points, b.points)
    else:  # float32 fields of a bag
        np.testing.assert_allclose(a.points, b.points, rtol=1e-6, atol=1e-6)
    for k in a.attributes:
        assert np.array_equal(a[k], b[k]), k


def test_windows_and_shots(frames, rec):
    assert [f.index for f in frames] == [0, 1]
    assert [(f.start, f.end) for f in frames] == [(0.0, 0.02), (0.02, 0.04)]
    assert sum(f.counts.shots for f in frames) == rec.n_shots == 800
    for f in frames:
        inside = (rec.shot_time >= f.start) & (rec.shot_time < f.end)
        assert f.counts.shots == int(inside.sum())
        assert f.counts.points == len(f.cloud) > 10
        assert f.cloud["age"].dtype == np.int32 and f.cloud["t"].dtype == np.float64


def test_point_time_is_the_mean_time_of_its_laser_returns(rec):
    """Without fusion, each point's t is the mean time of the shots whose detections it
    counted: inside the span of its pixel's true laser returns in the frame
    (/truth/label, independent of the pipeline) and, over the points, within 1 ms of
    their mean time (a frame holds only a few scan passes per pixel)."""
    lab = rec.truth["label"]
    diffs = []
    for f in iter_frames(rec, frame_rate=50, fusion=False):
        c = f.cloud
        assert np.all((c["t"] >= f.start) & (c["t"] < f.end)) and np.all(c["age"] == 1)
        inside = (rec.shot_time >= f.start) & (rec.shot_time < f.end)
        for j in range(len(c)):
            tr = rec.shot_time[inside & (lab[:, c["row"][j], c["pixel"][j]] == 1)]
            assert tr.min() - 1e-9 <= c["t"][j] <= tr.max() + 1e-9
            diffs.append(c["t"][j] - tr.mean())
    assert abs(np.mean(diffs)) < 1e-3


def test_point_time_follows_the_shots_that_saw_the_point(rec):
    """Shots of the second half of each 20 ms frame blanked: every point's t lies in the
    first half."""
    blank = (rec.shot_time % 0.02) >= 0.01
    bins = np.where(blank[:, None, None], 0, rec.bins).astype(np.uint16)
    cut = Recording(rec.system, rec.shot_time, bins, rec.zero_crossings, rec.rising)
    for f in iter_frames(cut, frame_rate=50, fusion=False):
        assert len(f.cloud) > 5
        assert np.all(f.cloud["t"] < f.start + 0.01)


def test_fusion_grows_age_on_the_static_room(frames):
    a, b = frames
    assert np.all(a.cloud["age"] == 1)
    both = np.intersect1d(a.cloud["pixel"], b.cloud["pixel"])
    aged = b.cloud["age"][np.isin(b.cloud["pixel"], both)]
    assert np.mean(aged == 2) > 0.8
    fused = b.cloud["age"] == 2
    prev = {p: (s, r) for p, s, r in zip(a.cloud["pixel"], a.cloud["sigma_r"], a.cloud["range"])}
    # a fused σ is below both frames' σ (inverse-variance sum) where the two frames agree
    # within their σ (else the history's Birge ratio widens it: at a turning column the
    # nominal system's stereo and the time of flight differ by a metre)
    own = iter_frames(ROOM, frame_rate=50, fusion=False)
    next(own)
    alone = next(own).cloud
    mine = {p: (s, r) for p, s, r in zip(alone["pixel"], alone["sigma_r"], alone["range"])}
    calm = [p for p in b.cloud["pixel"][fused]
            if (prev[p][1] - mine[p][1]) ** 2 <= prev[p][0] ** 2 + mine[p][0] ** 2]
    assert len(calm) >= 0.5 * fused.sum()
    fused_sigma = dict(zip(b.cloud["pixel"][fused], b.cloud["sigma_r"][fused]))
    assert all(fused_sigma[p] < min(prev[p][0], mine[p][0]) for p in calm)


@pytest.mark.parametrize("chunks", [37, 8192])
def test_the_same_frames_whatever_the_chunking(frames, rec, chunks):
    got = list(iter_frames(recording_chunks(rec, chunks), frame_rate=50))
    assert [(f.index, f.start, f.end) for f in got] == [(f.index, f.start, f.end)
                                                        for f in frames]
    for f, g in zip(frames, got):
        same_clouds(f.cloud, g.cloud)
        assert f.counts == g.counts


def test_processor_returns_frames_as_they_complete(rec):
    proc = FrameProcessor(rec.system, frame_shots=300)
    done = []
    for chunk in recording_chunks(rec, 100):
        done.append(len(proc.push(chunk)))
        assert proc.pending_shots <= 300 + 100
    # a frame of 300 shots is complete once a shot one mechanical period (13 shots)
    # after its last has arrived: after shots 400 and 700
    assert done == [0, 0, 0, 1, 0, 0, 1, 0]
    last = proc.flush()
    assert len(last) == 1 and last[0].counts.shots == 200 and proc.frames_done == 3
    assert last[0].start == rec.shot_time[600]


def test_frame_shots_matches_frame_rate_on_whole_frames(frames):
    got = list(iter_frames(ROOM, frame_shots=400))
    for f, g in zip(frames, got):
        same_clouds(f.cloud, g.cloud)


def test_bad_sources_and_options(rec):
    with pytest.raises(OptionError, match="exactly one"):
        FrameProcessor(rec.system, frame_rate=10, frame_shots=5)
    with pytest.raises(OptionError, match="frame_rate"):
        FrameProcessor(rec.system, frame_rate=-1)
    with pytest.raises(FormatError, match="Recordings"):
        list(iter_frames([np.zeros(3)], frame_rate=10))
    proc = FrameProcessor(rec.system, frame_rate=50)
    half = Recording(rec.system, rec.shot_time[:10], rec.bins[:10], rec.zero_crossings,
                     rec.rising)
    proc.push(half)
    with pytest.raises(FormatError, match="increasing"):
        proc.push(half)
    with pytest.raises(FormatError, match="bins"):
        proc.push(Recording(rec.system, rec.shot_time[10:12], rec.bins[10:13, :, :5],
                            rec.zero_crossings, rec.rising))


@pytest.mark.parametrize("fmt", ["ply", "las"])
def test_cli_folder_of_frames_is_iter_frames(frames, tmp_path, monkeypatch, fmt):
    monkeypatch.chdir(tmp_path)
    assert main(["process", "-q", ROOM, "--frame-rate", "50", "-o", "out/",
                 "--frame-format", fmt]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        f"room_00000{i}.{fmt}" for i in range(2)]
    for f in frames:
        back = read_cloud(frame_path(tmp_path / "out", "room", f.index, fmt))
        if fmt == "las":  # coordinates at 0.1 mm, attributes exact
            np.testing.assert_allclose(back.points, f.cloud.points, atol=5e-5)
            for k in f.cloud.attributes:
                assert np.array_equal(back[k], f.cloud[k]), k
        else:
            same_clouds(f.cloud, back)


def test_cli_bag_of_frames_is_stamped_with_the_frame_starts(frames, tmp_path):
    out = tmp_path / "room.mcap"
    assert main(["process", "-q", ROOM, "--frame-shots", "400", "-o", str(out)]) == 0
    got = read_frames_bag(out)
    assert [s for s, _ in got] == [round(f.start * 1e9) for f in frames]
    for f, (_, c) in zip(frames, got):
        same_clouds(f.cloud, c, exact_points=False)


@pytest.mark.parametrize("argv, where", [
    (["--frame-rate", "10", "--frame-shots", "5", "-o", "d/"], "--frame-rate"),
    (["--frame-rate", "0", "-o", "d/"], "--frame-rate"),
    (["--frame-rate", "10", "-o", "c.ply"], "--output"),
    (["--frame-rate", "10", "-o", "d/", "--labels", "l.h5"], "--labels"),
    (["--frame-rate", "10", "-o", "a/b/"], "--output"),
])
def test_cli_refusals_write_nothing(tmp_path, monkeypatch, capsys, argv, where):
    monkeypatch.chdir(tmp_path)
    assert main(["process", ROOM] + argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and where in err[0]
    assert list(tmp_path.iterdir()) == []


def test_chunks_carrying_only_their_own_zero_crossings(frames, rec):
    """A live source's chunks carry the crossings within one mechanical period of their
    shots, not the recording's: the same frames."""
    m = 1.0 / rec.system.scanner.f_mech
    chunks = []
    for c in recording_chunks(rec, 150):
        near = (c.zero_crossings >= c.shot_time[0] - m) & (c.zero_crossings <= c.shot_time[-1] + m)
        chunks.append(Recording(c.system, c.shot_time, c.bins, c.zero_crossings[near],
                                c.rising[near], c.truth, "live"))
    got = list(iter_frames(iter(chunks), frame_rate=50))
    assert len(got) == len(frames)
    for f, g in zip(frames, got):
        same_clouds(f.cloud, g.cloud)
