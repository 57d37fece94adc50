"""Dask scale-out: a 2-worker LocalCluster gives results identical to one process."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.pipeline.block_fusion import join_clouds, peak_blocks, split_peak_counts
from mems_stereo.pipeline.dask_plan import shot_ranges
from mems_stereo.pipeline.dask_setup import WORKER_MALLOC_ENV, dask_client
from mems_stereo.pipeline.distributed import process_many, process_split, recording_slots
from mems_stereo.pipeline.first_photon_correction import FP_BLOCK
from mems_stereo.pipeline.pass2 import PeakCounts, encode_peak_keys
from mems_stereo.pipeline.run import process_recording

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
# one pytest-xdist worker runs this module: one LocalCluster (the ``client`` fixture;
# tests/conftest.py: XDIST_GROUPS)
#: the client's environment before any cluster (restored once the workers started)
_ENV_KEYS = [*WORKER_MALLOC_ENV, "NUMBA_THREADING_LAYER"]
_ENV_BEFORE = {k: os.environ.get(k) for k in _ENV_KEYS}


def test_shot_ranges_cover_everything_once():
    r = shot_ranges(1001, 4)
    assert r[0][0] == 0 and r[-1][1] == 1001
    assert all(a[1] == b[0] for a, b in zip(r[:-1], r[1:]))


@functools.cache
def reference(name: str):
    """``process_recording(SAMPLES / name)`` with the defaults, in this process: the
    one-process result the split, parallel and blocked runs are compared with, computed
    once per file (each test asks for it before it patches anything; read only)."""
    return process_recording(SAMPLES / name)


@pytest.fixture(scope="module")
def client():
    with dask_client("local", n_workers=2) as c:
        yield c


def _same(a, b):
    for k in a.histograms:
        np.testing.assert_array_equal(a.histograms[k], b.histograms[k])
    np.testing.assert_array_equal(a.cloud.points, b.cloud.points)
    for k in a.cloud.attributes:
        np.testing.assert_array_equal(a.cloud[k], b.cloud[k])
    assert a.counts == b.counts and a.truth == b.truth
    # the shots' angles (process_split's parts compute their own on the workers)
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(a.valid, b.valid)


@pytest.mark.parametrize("table_state", ["cold", "complete"])
def test_split_computes_angles_on_the_workers_and_fills_missing_rows(client, monkeypatch,
                                                                     tmp_path, table_state):
    """The parts compute their shots' angles; the table rows they need and lack are
    filled on the workers before pass 1 (cold: an empty disk cache), and none are
    asked for when the table holds every row (complete: no round trip)."""
    import mems_stereo.pipeline.dask_split as D
    from mems_stereo.io.recording import read_header
    from mems_stereo.pipeline.angles import shot_angles
    from mems_stereo.pipeline.intervals import IntervalTable
    from mems_stereo.pipeline.settings import Settings

    one = reference("room.h5")
    monkeypatch.setenv("MEMS_STEREO_CACHE", str(tmp_path))  # cold: nothing cached
    filled = []
    fill = D.fill_table

    def counting_fill(client_, table, rows=None, **kw):
        filled.append(np.asarray(rows))
        return fill(client_, table, rows, **kw)

    monkeypatch.setattr(D, "fill_table", counting_fill)
    h = read_header(SAMPLES / "room.h5")
    th, va = shot_angles(h, h.system)
    table = IntervalTable.for_settings(h.system, Settings())
    used = table.missing(table.rows(th, va))
    if table_state == "complete":  # the rows the sample uses, and every other marked held
        table.ensure(used)  # (never read: no shot falls there)
        table.filled[:] = True
        monkeypatch.setattr(D.IntervalTable, "for_settings", lambda *a, **k: table)
    split = process_split(SAMPLES / "room.h5", scheduler=client, n_parts=3)
    _same(one, split)
    if table_state == "cold":
        assert len(filled) == 1 and np.array_equal(filled[0], used)  # the rows needed
    else:
        assert filled == []


def test_split_recording_equals_one_process(client):
    one = reference("room.h5")
    split = process_split(SAMPLES / "room.h5", scheduler=client, n_parts=5)
    _same(one, split)
    # the parts are summed on the workers: the client receives one pass-1 result's
    # uint32 raw + signal histograms (the (P, S) per-angle counts stay on the workers,
    # where the peak detector scores blocks of pixels), a few numbers per pixel and the
    # peak blocks' means
    P, S = 192, 9140
    one_result = P * 4097 * 4 * 2
    t = split.timings
    assert t["parts"] == 5
    # the fusion ran on the workers in blocks of peaks (room: 78 peaks, 5 blocks of 16)
    assert t["peak_blocks"] >= 2
    assert one_result <= t["client_bytes"] < one_result + 1e6 < one_result + P * S * 4
    assert 0 <= t["peaks_wait"] <= t["peaks"]
    # a time is reported (how it compares with the stages is the benchmark's business:
    # wall times on a loaded machine make no test)
    assert t["client_serial"] > 0


def test_many_recordings_equal_one_process(client):
    paths = [SAMPLES / "room.h5", SAMPLES / "calib_2.5m.h5", SAMPLES / "room.h5"]
    # submitted largest first: the results still come back in the order given
    sizes = [recording_slots(p) for p in paths]
    assert sizes[0] != sizes[1] and min(sizes) > 0
    assert recording_slots(SAMPLES / "no such file.h5") == 0
    res = process_many(paths, scheduler=client)
    for p, r in zip(paths, res):
        _same(reference(p.name), r)


def test_local_workers_get_one_malloc_arena_and_the_client_keeps_its_environ(client):
    got = client.run(lambda: {k: os.environ.get(k) for k in WORKER_MALLOC_ENV})
    assert got and all(v == WORKER_MALLOC_ENV for v in got.values())
    # Dask's pre-spawn environment lands in the spawning process, and the workers'
    # threading layer is set there for them to inherit: both restored there
    assert {k: os.environ.get(k) for k in _ENV_KEYS} == _ENV_BEFORE
    threading = client.run(lambda: os.environ.get("NUMBA_THREADING_LAYER"))
    assert threading and all(v is not None for v in threading.values())


def test_peak_blocks_cut_at_the_fusion_block_and_balance_work():
    rng = np.random.default_rng(14)
    for _ in range(200):
        Q = int(rng.integers(0, 300))
        e = rng.integers(0, 5000, Q)
        n = int(rng.integers(1, 20))
        b = peak_blocks(e, n)
        if Q == 0:
            assert b == []
            continue
        assert b[0][0] == 0 and b[-1][1] == Q and len(b) <= n
        assert all(x[1] == y[0] for x, y in zip(b[:-1], b[1:]))
        assert all(q0 % FP_BLOCK == 0 for q0, _ in b)
        if Q >= FP_BLOCK * n * 4 and n > 1:  # enough cuts: every block near 1/n of the work
            w = np.array([e[q0:q1].sum() + (q1 - q0) for q0, q1 in b], float)
            assert len(b) == n
            assert w.max() <= (e.sum() + Q) / n + FP_BLOCK * e.max() + FP_BLOCK


def test_split_peak_counts_renumbers_each_block():
    rng = np.random.default_rng(15)
    S, nb, Q = 50, 33, 70
    q = rng.integers(0, Q, 2000)
    k = encode_peak_keys(q, rng.integers(0, S, q.size), rng.integers(1, nb, q.size), S, nb)
    pc = PeakCounts()
    pc.add_keys(k)
    pc = pc.finished()
    blocks = split_peak_counts(pc, Q, S, nb, 3)
    assert sum(len(b.counts.keys) for b in blocks) == pc.keys.size
    for b in blocks:
        q0, q1, sub = b.start, b.stop, b.counts
        back = sub.keys + q0 * S * nb
        a, b = np.searchsorted(pc.keys, [q0 * S * nb, q1 * S * nb])
        np.testing.assert_array_equal(back, pc.keys[a:b])
        np.testing.assert_array_equal(sub.counts, pc.counts[a:b])
        assert sub.keys.min() >= 0 and sub.keys.max() < (q1 - q0) * S * nb


def test_join_clouds_fills_missing_first_photon_attributes():
    from mems_stereo.pipeline.cloud import PointCloud

    a = PointCloud(np.ones((2, 3)), {"counts": np.ones(2, np.int32), "tof_delay": np.ones(2),
                                     "z": np.zeros(2)})
    b = PointCloud(np.zeros((1, 3)), {"counts": np.ones(1, np.int32), "z": np.ones(1)})
    j = join_clouds([b, a])
    assert list(j.attributes) == ["counts", "tof_delay", "z"]
    assert np.isnan(j["tof_delay"][0]) and j["tof_delay"][1:].tolist() == [1.0, 1.0]


@pytest.mark.parametrize("run_ends", [False, True])
def test_fusion_of_peak_blocks_equals_the_whole(monkeypatch, run_ends):
    """The fusion split at multiples of FP_BLOCK peaks, joined, is the whole's cloud,
    bit for bit (its first-photon step works in blocks of FP_BLOCK peaks by index, and
    each block fuses a halo of its row neighbours for the depth edges; with the run
    ends counted as edges nearly every cut separates two neighbours)."""
    from mems_stereo.pipeline import block_fusion as R
    from mems_stereo.pipeline import peak_means
    from mems_stereo.pipeline.block_fusion import cloud_of_means, means_block, points_block

    monkeypatch.setattr(peak_means, "EDGE_RUN_ENDS", run_ends)

    for name in ("room.h5", "floodlight.h5"):
        seen = {}
        orig = R.points_from_counts

        def spy(system, peaks, counts, st, shots_per_step=None, table=None, seen=seen,
                orig=orig):
            seen.update(system=system, peaks=peaks, counts=counts, st=st, sps=shots_per_step,
                        table=table)
            return orig(system, peaks, counts, st, shots_per_step=shots_per_step, table=table)

        R.points_from_counts = spy
        try:
            whole = process_recording(SAMPLES / name).cloud
        finally:
            R.points_from_counts = orig
        light = seen["peaks"].light()
        Q = len(light)
        S, nb = seen["table"].n_steps, seen["system"].tdc.n_bins + 1
        for n in (2, 3, 7, Q):
            blocks = split_peak_counts(seen["counts"], Q, S, nb, n)
            assert len(blocks) > 1
            j = join_clouds([points_block(seen["system"], light, blocks, i, seen["st"],
                                           seen["sps"], seen["table"])
                             for i in range(len(blocks))])
            # the Dask runner's form: each block's peak means without a halo, joined,
            # and the cloud (depth edges) made from them
            m = cloud_of_means([means_block(seen["system"], light, blocks, i, seen["st"],
                                            seen["sps"], seen["table"])
                                for i in range(len(blocks))], seen["st"])
            for c in (j, m):
                assert list(c.attributes) == list(whole.attributes)
                np.testing.assert_array_equal(c.points, whole.points)
                for k in whole.attributes:
                    np.testing.assert_array_equal(c[k], whole[k], err_msg=k)


def _count_calls(monkeypatch, module, name: str) -> list:
    """Wrap ``module.name`` so that each call appends to the returned list."""
    calls = []
    orig = getattr(module, name)

    def counted(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    monkeypatch.setattr(module, name, counted)
    return calls


def test_process_recording_fusing_in_blocks_equals_one_block(monkeypatch):
    """Bounded memory: the fusion of a run in blocks of at most FUSE_ENTRIES entries
    (each block's per-peak sums, joined into one accumulator) gives the cloud of one
    block, bit for bit."""
    from mems_stereo.pipeline import block_fusion as R

    one = reference("room.h5")
    monkeypatch.setattr(R, "FUSE_ENTRIES", 300)
    calls = _count_calls(monkeypatch, R, "peak_sums_from_counts")
    blocked = process_recording(SAMPLES / "room.h5")
    assert len(calls) >= 2
    _same(one, blocked)


def test_peak_counts_merge_equals_unique_count():
    """PeakCounts' sorted merge (integer, in place) against np.unique counts, over
    random streams of keys added in random chunks and summed in random groups."""
    rng = np.random.default_rng(16)
    for _ in range(60):
        n_keys = int(rng.integers(1, 5000))
        stream = rng.integers(0, n_keys, int(rng.integers(0, 20000))) * 7 + 3
        ref_k, ref_c = np.unique(stream, return_counts=True)
        cuts = np.sort(rng.integers(0, stream.size + 1, int(rng.integers(0, 12))))
        parts = []
        for chunk in np.split(stream, cuts):
            pc = PeakCounts()
            for sub in np.array_split(chunk, int(rng.integers(1, 5))):
                pc.add_keys(sub)
                if rng.random() < 0.5:
                    pc.merge_pending()
            parts.append(pc.finished())
        total = parts[0]
        for p in parts[1:]:
            total = total + p
        np.testing.assert_array_equal(total.keys, ref_k)
        np.testing.assert_array_equal(total.counts, ref_c)
        assert total.counts.dtype == np.int64 and total.keys.dtype == np.int64
        assert all(np.all(np.diff(p.keys) > 0) for p in parts)


def test_trimming_the_heap_between_stages_changes_nothing(monkeypatch):
    """With TRIM_SLOTS = 0 every run hands freed heap back between its stages
    (glibc malloc_trim; a no-op elsewhere): same result, and it did run."""
    from mems_stereo.pipeline import run as R
    from mems_stereo.util import memory

    one = reference("room.h5")
    calls = []
    orig = memory.release_freed_memory

    def spy():
        calls.append(orig())
        return calls[-1]

    monkeypatch.setattr(R, "TRIM_SLOTS", 0)
    monkeypatch.setattr(memory, "release_freed_memory", spy)
    _same(one, process_recording(SAMPLES / "room.h5"))
    assert len(calls) == 4


def test_split_with_signal_stores_equals_one_process(monkeypatch):
    """process_split whose parts keep their signal detections for pass 2 (forced on
    the small sample; threads, so the forcing reaches the workers) gives the one
    process's result, bit for bit; a store pickled between processes keeps its keys."""
    import pickle

    from distributed import Client, LocalCluster

    import mems_stereo.pipeline.dask_tasks as D
    import mems_stereo.pipeline.pass1 as pass1
    from mems_stereo.pipeline.signal_store import SignalStore

    one = process_recording(SAMPLES / "floodlight.h5")
    used = _count_calls(monkeypatch, D, "peak_counts_from_store")
    monkeypatch.setattr(D, "COMPILE_SLOTS", 0)
    monkeypatch.setattr(pass1, "COMPILE_SLOTS", 0)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as c:
        split = process_split(SAMPLES / "floodlight.h5", scheduler=c, n_parts=3)
    # each of the 3 parts' stores counted once: the first stage's peaks and the matched
    # filter's candidates over widened windows in one pass, from which the candidates',
    # the first stage's and the confirmed peaks' counts are filtered (the floodlight
    # sample confirms some)
    assert len(used) == 3
    _same(one, split)
    st = SignalStore(memory_bytes=16)
    st.append(np.arange(10))
    st.append(np.arange(5))
    back = pickle.loads(pickle.dumps(st))
    np.testing.assert_array_equal(np.concatenate(list(back.blocks())),
                                  np.r_[np.arange(10), np.arange(5)])
    assert back.n_keys == 15 and back.complete


def test_deal_blocks_balances_by_work():
    """Largest first to the least loaded worker: on random work the busiest worker
    carries at most 4/3 of the optimum's bound (Graham), every block once."""
    from mems_stereo.pipeline.dask_plan import deal_blocks

    rng = np.random.default_rng(14)
    worst = 0.0
    for _ in range(200):
        n, w = int(rng.integers(1, 30)), int(rng.integers(1, 5))
        work = rng.exponential(1.0, n).tolist()
        owner = deal_blocks(work, [f"w{i}" for i in range(w)])
        assert len(owner) == n and set(owner) <= {f"w{i}" for i in range(w)}
        load = {}
        for o, x in zip(owner, work):
            load[o] = load.get(o, 0.0) + x
        bound = max(sum(work) / w, max(work))  # no assignment does better
        worst = max(worst, max(load.values()) / bound)
    assert worst <= 4 / 3 + 1e-9
    assert deal_blocks([1.0, 2.0], []) == [None, None]
    print(f"busiest worker / lower bound, worst of 200: {worst:.3f}")


def test_block_slots_hold_every_block_once_within_each_workers_slots():
    """Slot s runs on worker s mod n: every block in exactly one slot, at most
    ``per_worker`` a worker, each worker's blocks those deal_blocks gives it (capped),
    in block order; empty slots -1."""
    from mems_stereo.errors import OptionError
    from mems_stereo.pipeline.dask_plan import block_slots, deal_blocks

    rng = np.random.default_rng(15)
    for _ in range(200):
        n_w, per = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        n = int(rng.integers(0, n_w * per + 1))
        work = rng.exponential(1.0, n).tolist()
        slots = block_slots(work, n_w, per)
        assert len(slots) == n_w * per
        assert sorted(b for b in slots if b >= 0) == list(range(n))
        owner = deal_blocks(work, list(range(n_w)), per)
        for w in range(n_w):
            mine = [b for b in slots[w::n_w] if b >= 0]
            assert mine == sorted(mine) == [b for b in range(n) if owner[b] == w]
            assert len(mine) <= per
    # the cap: one large block and four small on two workers: 1 + 4 by work alone,
    # 2 + 3 with three slots each
    assert sorted(np.bincount(np.array(deal_blocks([10.0, 1, 1, 1, 1], [0, 1])))) == [1, 4]
    assert sorted(np.bincount(np.array(deal_blocks([10.0, 1, 1, 1, 1], [0, 1], 3)))) == [2, 3]
    with pytest.raises(OptionError, match="do not fit"):
        deal_blocks([1.0] * 5, [0, 1], 2)


def test_fusion_work_counts_entries_and_steps():
    """Per peak: its distinct (step, code) keys plus BACKGROUND_SEGMENTS per distinct step."""
    from mems_stereo.pipeline.block_fusion import fusion_work
    from mems_stereo.pipeline.window_background import BACKGROUND_SEGMENTS

    rng = np.random.default_rng(3)
    Q, S, nb = 9, 50, 20
    q, j, c = rng.integers(0, Q, 400), rng.integers(0, S, 400), rng.integers(0, nb, 400)
    keys = np.unique((q * S + j) * nb + c)
    pc = PeakCounts(keys, np.ones(keys.size, np.int64))
    got = fusion_work(pc, Q, S, nb)
    kq, kj = keys // (S * nb), (keys // nb) % S
    want = [np.sum(kq == p) + BACKGROUND_SEGMENTS * np.unique(kj[kq == p]).size
            for p in range(Q)]
    assert np.array_equal(got, want)
    assert np.array_equal(fusion_work(PeakCounts(), Q, S, nb), np.zeros(Q))


@pytest.mark.parametrize("compiled", [False, True])
def test_select_counts_filters_and_renumbers_exactly(monkeypatch, compiled):
    """pass2.select_counts: the counts of some peaks over sub-windows of their steps,
    renumbered, equal the counts of exactly those keys (random keys and windows), in
    NumPy and in its compiled pass (numba loaded, any number of keys)."""
    import mems_stereo.pipeline.pass2 as pass2
    from mems_stereo.pipeline.pass2 import CountSelection, decode_peak_keys, select_counts

    if compiled:
        pytest.importorskip("numba")
        monkeypatch.setattr(pass2, "MERGE_COMPILED_KEYS", 0)
    else:
        monkeypatch.setattr(pass2, "MERGE_COMPILED_KEYS", 10 ** 12)

    rng = np.random.default_rng(1419)
    S, nb = 50, 9
    for _ in range(20):
        Q = int(rng.integers(1, 12))
        keys = np.unique(encode_peak_keys(rng.integers(0, Q, 400), rng.integers(0, S, 400),
                                          rng.integers(1, nb, 400), S, nb))
        pc = PeakCounts(keys, rng.integers(1, 9, keys.size))
        src = rng.permutation(Q)[:int(rng.integers(0, Q + 1))]
        dst = rng.permutation(src.size)
        lo = rng.integers(0, S, src.size)
        hi = lo + rng.integers(-1, S, src.size)
        got = select_counts(pc, CountSelection(src, dst, lo, hi), S, nb)
        q, step, code = decode_peak_keys(pc.keys, S, nb)
        want = {}
        for s_, d_, a, b in zip(src, dst, lo, hi):
            for k in np.flatnonzero((q == s_) & (step >= a) & (step <= b)):
                want[int((d_ * S + step[k]) * nb + code[k])] = pc.counts[k]
        assert np.all(np.diff(got.keys) > 0)
        assert dict(zip(got.keys.tolist(), got.counts.tolist())) == want


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_peak_counts_sum_compiled_equals_numpy(monkeypatch, seed):
    """PeakCounts + PeakCounts merged in one compiled pass (numba loaded) equals the
    NumPy merge (merge_sorted_counts): keys in one, the other or both, and empty sets."""
    pytest.importorskip("numba")
    import mems_stereo.pipeline.pass2 as pass2

    rng = np.random.default_rng(seed)
    for na, nb in ((3000, 5000), (1, 4000), (0, 10), (2500, 0)):
        pool = np.unique(rng.integers(0, 20000, 9000))
        a = np.sort(rng.choice(pool, min(na, pool.size), replace=False))
        b = np.sort(rng.choice(pool, min(nb, pool.size), replace=False))
        ca, cb = rng.integers(1, 50, a.size), rng.integers(1, 50, b.size)
        monkeypatch.setattr(pass2, "MERGE_COMPILED_KEYS", 0)
        got = PeakCounts(a, ca) + PeakCounts(b, cb)
        monkeypatch.setattr(pass2, "MERGE_COMPILED_KEYS", 10 ** 12)
        want = PeakCounts(a, ca) + PeakCounts(b, cb)
        assert np.array_equal(got.keys, want.keys) and np.array_equal(got.counts, want.counts)
        assert np.intersect1d(a, b).size > 0 or min(a.size, b.size) <= 1


def test_placement_without_known_workers_lets_dask_choose():
    """No worker addresses (the scheduler listed none yet): no placement keywords, which
    Dask would refuse (allow_other_workers needs workers)."""
    from mems_stereo.pipeline.dask_setup import on_worker

    assert on_worker([], 3) == {}
    assert on_worker(["a", "b"], 3) == {"workers": ["b"], "allow_other_workers": True}
