"""Time-tagger import: PTU T2/T3 records, Photon-HDF5, the mapping, the first-photon rule."""

from __future__ import annotations

import importlib.util
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.cli import main as cli_main
from mems_stereo.errors import FormatError
from mems_stereo.io.photon_hdf5 import photon_hdf5_stream, write_photon_hdf5_events
from mems_stereo.io.ptu import (
    MARKER,
    PHOTON,
    SYNC,
    encode_t2,
    encode_t3,
    iter_ptu_events,
    ptu_stream,
    read_ptu_header,
    recording_to_ptu,
    write_ptu,
)
from mems_stereo.io.realdata import load_realdata_npz
from mems_stereo.io.recording import read_recording
from mems_stereo.io.tttr import events_to_recording, events_to_timetags
from mems_stereo.io.tttr_map import load_map, map_from_dict
from mems_stereo.model.system import burkard2022
from mems_stereo.sim import load_scene, simulate

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _small_system(width=16):
    s = burkard2022()
    K = np.array(s.receiver.camera_matrix, dtype=np.float64)
    K[0, 2] = (width - 1) / 2.0
    return s.replace(receiver=replace(s.receiver, image_size=(width, 1), camera_matrix=K))


@pytest.fixture(scope="module")
def small_rec():
    return simulate(_small_system(24), load_scene(SAMPLES / "room_scene.json"), 2000,
                    rng=np.random.default_rng(7), background_hz=3e5)


def _events(stream_blocks):
    bl = list(stream_blocks)
    return tuple(np.concatenate([getattr(b, k) for b in bl]) for k in
                 ("macro", "micro", "kind", "channel"))


# ----------------------------------------------------------------------------- records
def test_t2_encode_decode_any_block_size(tmp_path):
    rng = np.random.default_rng(1)
    n = 3000
    # time jumps up to 3e9 ticks: several wraps of 2^25, some needing 2 overflow records
    t = np.cumsum(rng.integers(0, 1 << 26, n) * (rng.random(n) < 0.3)
                  + rng.integers(0, 1000, n)).astype(np.int64)
    t[1500] = t[1499] + (1 << 25) * 40_000_000  # > 2^25 - 1 wraps: two overflow records
    t[1501:] += t[1500] - t[1499]
    kind = rng.choice([PHOTON, SYNC, MARKER], n).astype(np.int8)
    ch = np.where(kind == PHOTON, rng.integers(0, 63, n),
                  np.where(kind == MARKER, rng.integers(1, 16, n), 0))
    rec = encode_t2(t, kind, ch)
    assert rec.size > n  # overflow records were inserted
    write_ptu(tmp_path / "a.ptu", "T2", rec, global_resolution=5e-12, resolution=5e-12,
              sync_rate=2e4)
    h = read_ptu_header(tmp_path / "a.ptu")
    assert (h.mode, h.n_records, h.global_resolution) == ("T2", rec.size, 5e-12)
    for chunk in (7, 1000, 1 << 22):
        mac, mic, kd, c = _events(ev for _, ev in iter_ptu_events(tmp_path / "a.ptu", chunk))
        np.testing.assert_array_equal(mac, t)
        np.testing.assert_array_equal(kd, kind)
        np.testing.assert_array_equal(c, ch)
        assert not mic.any()


def test_t2_photons_and_markers_agree_with_ptufile(tmp_path):
    """ptufile decodes the same records independently (it folds the sync into channel 0)."""
    import ptufile

    rng = np.random.default_rng(2)
    n = 2000
    t = np.cumsum(rng.integers(0, 1 << 24, n)).astype(np.int64)
    kind = rng.choice([PHOTON, MARKER, SYNC], n, p=[0.7, 0.1, 0.2]).astype(np.int8)
    ch = np.where(kind == PHOTON, rng.integers(1, 40, n), np.where(kind == MARKER,
                                                                   rng.integers(1, 16, n), 0))
    write_ptu(tmp_path / "b.ptu", "T2", encode_t2(t, kind, ch), global_resolution=1e-12,
              resolution=1e-12, sync_rate=2e4)
    with ptufile.PtuFile(tmp_path / "b.ptu") as p:
        d = p.decode_records()
    ph = d["channel"] > 0  # photons of channels >= 1 (channel 0 = sync in ptufile's T2)
    np.testing.assert_array_equal(d["time"][ph].astype(np.int64), t[kind == PHOTON])
    np.testing.assert_array_equal(d["channel"][ph], ch[kind == PHOTON])
    mk = d["marker"] > 0
    np.testing.assert_array_equal(d["time"][mk].astype(np.int64), t[kind == MARKER])


def test_t3_blocks_carry_overflows(tmp_path):
    rng = np.random.default_rng(3)
    n = 2500
    ns = np.cumsum(rng.integers(0, 3000, n) * (rng.random(n) < 0.5)).astype(np.int64)
    kind = rng.choice([PHOTON, MARKER], n, p=[0.9, 0.1]).astype(np.int8)
    dt = np.where(kind == PHOTON, rng.integers(0, 32768, n), 0)
    ch = np.where(kind == PHOTON, rng.integers(0, 63, n), rng.integers(1, 16, n))
    write_ptu(tmp_path / "c.ptu", "T3", encode_t3(ns, dt, kind, ch), global_resolution=5e-5,
              resolution=3.125e-10, sync_rate=2e4)
    for chunk in (5, 333, 1 << 22):
        mac, mic, kd, c = _events(ev for _, ev in iter_ptu_events(tmp_path / "c.ptu", chunk))
        np.testing.assert_array_equal(mac, ns)
        np.testing.assert_array_equal(mic, dt)
        np.testing.assert_array_equal(kd, kind)
        np.testing.assert_array_equal(c, ch)


def test_encoder_refuses_what_generic_records_cannot_hold():
    with pytest.raises(ValueError, match="channel"):
        encode_t2([0], [PHOTON], [63])
    with pytest.raises(ValueError, match="non-decreasing"):
        encode_t2([5, 3], [PHOTON, PHOTON], [0, 0])
    with pytest.raises(ValueError, match="dtime"):
        encode_t3([0], [40000], [PHOTON], [0])


def test_not_a_ptu_file(tmp_path):
    (tmp_path / "x.ptu").write_bytes(b"not a ptu file at all" * 10)
    with pytest.raises(FormatError, match="x.ptu"):
        read_ptu_header(tmp_path / "x.ptu")


# ----------------------------------------------------------------------------- round trip
def _import(path, mapping, system, out, **kw):
    info, blocks = ptu_stream(path, kw.pop("chunk_records", 1 << 22))
    return events_to_recording(blocks, info, map_from_dict(mapping), system, out, **kw)


@pytest.mark.parametrize("chunk,window", [(1 << 22, 8192), (97, 13)])
def test_t2_round_trip_gives_the_same_recording(small_rec, tmp_path, chunk, window):
    m = recording_to_ptu(small_rec, tmp_path / "r.ptu", mode="T2")
    st = _import(tmp_path / "r.ptu", m, small_rec.system, tmp_path / "r.h5",
                 chunk_records=chunk, window_shots=window)
    r2 = read_recording(tmp_path / "r.h5")
    np.testing.assert_array_equal(r2.bins, small_rec.bins)
    np.testing.assert_allclose(r2.shot_time, small_rec.shot_time, rtol=0, atol=1e-15)
    tick = small_rec.system.tdc.bin_width / 64
    assert np.abs(r2.zero_crossings - small_rec.zero_crossings).max() <= tick / 2 + 1e-15
    np.testing.assert_array_equal(r2.rising, small_rec.rising)
    assert r2.system.tdc.bin_width == small_rec.system.tdc.bin_width
    assert st.written == np.count_nonzero(small_rec.bins) and st.not_first == 0


def test_t3_round_trip_bins_exact_monitor_on_the_sync_grid(small_rec, tmp_path):
    m = recording_to_ptu(small_rec, tmp_path / "r3.ptu", mode="T3")
    _import(tmp_path / "r3.ptu", m, small_rec.system, tmp_path / "r3.h5")
    r2 = read_recording(tmp_path / "r3.h5")
    np.testing.assert_array_equal(r2.bins, small_rec.bins)
    np.testing.assert_allclose(r2.shot_time, small_rec.shot_time, rtol=0, atol=1e-15)
    # a T3 marker carries only its sync count: quantised to the sync period (documented)
    d = small_rec.zero_crossings - r2.zero_crossings
    assert d.min() >= -1e-12 and d.max() < 1.0 / small_rec.system.laser.f_rep


def test_round_trip_processes_to_the_same_cloud(small_rec, tmp_path):
    from mems_stereo.pipeline import Settings, process_recording
    from mems_stereo.sim.simulate import write_simulation

    write_simulation(tmp_path / "orig.h5", small_rec)
    m = recording_to_ptu(small_rec, tmp_path / "r.ptu", mode="T2")
    _import(tmp_path / "r.ptu", m, small_rec.system, tmp_path / "r.h5")
    a = process_recording(tmp_path / "orig.h5", settings=Settings()).cloud
    b = process_recording(tmp_path / "r.h5", settings=Settings()).cloud
    assert len(a) == len(b) > 5
    c = small_rec.system.speed_of_light
    half_bin = 0.5 * c * small_rec.system.tdc.bin_width
    d = np.abs(a.points - b.points).max()
    assert d < half_bin
    assert d < 1e-6  # in fact identical up to the 4.9 ps time tag of the monitor
    for k in a.attributes:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-9)


def test_first_photon_rule_and_counters(tmp_path):
    sysm = _small_system(4)
    bw = sysm.tdc.bin_width
    tick = bw / 4
    P = 50_000_000  # sync period in ticks (tick = 78.125 ps → 3.9 ms, not physical; fine)
    sysm = sysm.replace(laser=replace(sysm.laser, f_rep=1.0 / (P * tick)))  # one shot a period
    sync_t = (np.arange(6) + 1) * P
    # shot 1, channel 2: photons in codes 5 and 3 → code 3 kept; channel 9 unmapped;
    # shot 2, channel 0: code n_bins + 1 (out of range); a photon before the first sync
    ev = [(sync_t[1] + 4 * 4, PHOTON, 2), (sync_t[1] + 2 * 4 + 3, PHOTON, 2),
          (sync_t[1] + 8, PHOTON, 9), (sync_t[2] + 4096 * 4, PHOTON, 0),
          (sync_t[3] + 0, PHOTON, 1), (sync_t[0] + 5, MARKER, 1), (sync_t[4] + 5, MARKER, 2)]
    t = np.concatenate([sync_t, [e[0] for e in ev], [0]])
    kind = np.concatenate([np.full(6, SYNC), [e[1] for e in ev], [PHOTON]]).astype(np.int8)
    ch = np.concatenate([np.zeros(6, int), [e[2] for e in ev], [3]])
    o = np.lexsort((kind != SYNC, t))
    t, kind, ch = t[o], kind[o], ch[o]
    write_ptu(tmp_path / "f.ptu", "T2", encode_t2(t, kind, ch), global_resolution=tick,
              resolution=tick, sync_rate=1.0 / (P * tick))
    m = {"format": "mems-stereo/tttr-map", "version": 1,
         "pixels": [[0, 0, 0], [1, 1, 0], [2, 2, 0], [3, 3, 0]],
         "zero_crossings": {"source": "marker", "rising_edge": 1, "falling_edge": 2},
         "tdc": {"binning": 4}}
    info, blocks = ptu_stream(tmp_path / "f.ptu", 3)
    st = events_to_recording(blocks, info, map_from_dict(m), sysm, tmp_path / "f.h5",
                             window_shots=2)
    r = read_recording(tmp_path / "f.h5")
    expect = np.zeros((6, 1, 4), np.uint16)
    expect[1, 0, 2] = 3  # (2·4 + 3) // 4 + 1
    expect[3, 0, 1] = 1
    np.testing.assert_array_equal(r.bins, expect)
    assert (st.photons, st.written, st.not_first, st.unmapped, st.out_of_range,
            st.outside_shots) == (6, 2, 1, 1, 1, 1)
    np.testing.assert_array_equal(r.rising, [1, 0])
    np.testing.assert_allclose(r.shot_time, sync_t * tick, rtol=1e-15)


def test_all_photons_go_to_the_timetag_layout(small_rec, tmp_path):
    m = recording_to_ptu(small_rec, tmp_path / "r.ptu", mode="T2")
    info, blocks = ptu_stream(tmp_path / "r.ptu")
    st = events_to_timetags(blocks, info, map_from_dict(m), small_rec.system,
                            tmp_path / "r.npz")
    d = load_realdata_npz(tmp_path / "r.npz")
    n = np.count_nonzero(small_rec.bins)
    assert st.written == n == d["timestamps_ps"].size
    counts = np.count_nonzero(small_rec.bins.reshape(small_rec.n_shots, -1), axis=0)
    np.testing.assert_array_equal(np.diff(d["offsets"]), counts)
    with np.load(tmp_path / "r.npz") as z:
        code, shot = z["code"], z["shot"]
    pix = np.repeat(np.arange(counts.size), counts)
    np.testing.assert_array_equal(small_rec.bins.reshape(small_rec.n_shots, -1)[shot, pix], code)
    bw_ps = small_rec.system.tdc.bin_width * 1e12
    np.testing.assert_allclose(d["timestamps_ps"], (code - 1) * bw_ps, atol=0.5)


def test_map_errors_name_the_field(tmp_path):
    base = {"format": "mems-stereo/tttr-map", "version": 1, "pixels": [[0, 0, 0]],
            "zero_crossings": {"source": "marker", "rising_edge": 1}}
    map_from_dict(base)
    for bad, fld in [({"pixels": [[0, 0]]}, "pixels[0]"),
                     ({"pixels": [[0, 0, 0], [0, 1, 0]]}, "pixels"),
                     ({"zero_crossings": {"source": "marker", "rising_edge": 7}},
                      "zero_crossings.rising_edge"),
                     ({"zero_crossings": {"source": "pin"}}, "zero_crossings.source"),
                     ({"tdc": {"binning": 0}}, "tdc.binning"),
                     ({"format": "x"}, "format")]:
        with pytest.raises(FormatError, match=fld.replace("[", r"\[").replace("]", r"\]")):
            map_from_dict(base | bad, "m.json")


# ----------------------------------------------------------------------------- Photon-HDF5
def _t2_events(rec, clock_ch=40, zc_ch=(41, 42)):
    """A recording as T2-like detector events (unit: bin_width / 8)."""
    bw = rec.system.tdc.bin_width
    unit = bw / 8
    origin = np.floor(min(rec.zero_crossings[0], 0.0) / 5e-5) * 5e-5
    st = np.rint((rec.shot_time - origin) / unit).astype(np.int64)
    k, p = np.nonzero(rec.bins.reshape(rec.n_shots, -1))
    code = rec.bins.reshape(rec.n_shots, -1)[k, p].astype(np.int64)
    zt = np.rint((rec.zero_crossings - origin) / unit).astype(np.int64)
    t = np.concatenate([st, st[k] + (code - 1) * 8, zt])
    det = np.concatenate([np.full(st.size, clock_ch), p,
                          np.where(rec.rising > 0, zc_ch[0], zc_ch[1])])
    first = np.concatenate([np.zeros(st.size), np.ones(t.size - st.size)])
    o = np.lexsort((first, t))
    mp = {"format": "mems-stereo/tttr-map", "version": 1,
          "pixels": [[i, i, 0] for i in range(rec.bins.shape[2])],
          "shot_clock": {"source": "channel", "channel": clock_ch},
          "zero_crossings": {"source": "channel", "rising_edge": zc_ch[0],
                             "falling_edge": zc_ch[1]},
          "tdc": {"binning": 8}, "time_origin": float(origin)}
    return t[o], det[o], unit, mp


def test_photon_hdf5_h5py_writer_round_trip(small_rec, tmp_path):
    t, det, unit, mp = _t2_events(small_rec)
    write_photon_hdf5_events(tmp_path / "p.h5", t, det, timestamps_unit=unit)
    info, blocks = photon_hdf5_stream(tmp_path / "p.h5", block=101)
    assert info.mode == "T2"
    events_to_recording(blocks, info, map_from_dict(mp), small_rec.system, tmp_path / "o.h5")
    r2 = read_recording(tmp_path / "o.h5")
    np.testing.assert_array_equal(r2.bins, small_rec.bins)
    np.testing.assert_array_equal(r2.rising, small_rec.rising)
    assert np.abs(r2.zero_crossings - small_rec.zero_crossings).max() <= unit


@pytest.mark.slow  # importing phconvert takes ~13 s (its PTU reader compiles with numba)
@pytest.mark.skipif(importlib.util.find_spec("phconvert") is None,
                    reason="phconvert (optional extra photon-hdf5) not installed")
def test_photon_hdf5_written_by_phconvert(small_rec, tmp_path):
    import warnings

    import phconvert as phc

    t, det, unit, mp = _t2_events(small_rec)
    dets = sorted(set(det.tolist()))
    data = dict(
        description="mems-stereo round trip",
        photon_data=dict(timestamps=t, detectors=det.astype(np.uint8),
                         timestamps_specs=dict(timestamps_unit=unit),
                         measurement_specs=dict(measurement_type="generic",
                                                detectors_specs={"spectral_ch1": dets})),
        setup=dict(num_pixels=len(dets), num_spots=1, num_spectral_ch=1,
                   num_polarization_ch=1, num_split_ch=1, modulated_excitation=False,
                   lifetime=False, excitation_alternated=[False], excitation_cw=[True]),
        identity=dict(author="test", author_affiliation="mems-stereo"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        phc.hdf5.save_photon_hdf5(data, h5_fname=str(tmp_path / "phc.hdf5"), overwrite=True,
                                  close=True)
    info, blocks = photon_hdf5_stream(tmp_path / "phc.hdf5")
    events_to_recording(blocks, info, map_from_dict(mp), small_rec.system, tmp_path / "o.h5")
    np.testing.assert_array_equal(read_recording(tmp_path / "o.h5").bins, small_rec.bins)


def test_photon_hdf5_t3_like_needs_sync_period_timestamps(small_rec, tmp_path):
    k, p = np.nonzero(small_rec.bins.reshape(small_rec.n_shots, -1))
    code = small_rec.bins.reshape(small_rec.n_shots, -1)[k, p]
    write_photon_hdf5_events(tmp_path / "n.h5", k, p, timestamps_unit=1e-6, nanotimes=code - 1,
                             tcspc_unit=small_rec.system.tdc.bin_width, tcspc_num_bins=4096,
                             laser_repetition_rate=2e4)
    with pytest.raises(FormatError, match="timestamps_unit"):
        photon_hdf5_stream(tmp_path / "n.h5")


# ----------------------------------------------------------------------------- sample + CLI
def test_sample_ptu_imports_to_its_simulated_recording(tmp_path, capsys):
    sys.path.insert(0, str(SAMPLES))
    try:
        from make_ptu_sample import room48_recording
    finally:
        sys.path.remove(str(SAMPLES))
    assert (SAMPLES / "room48.ptu").stat().st_size < 1_000_000
    out = tmp_path / "room48.h5"
    assert cli_main(["import", str(SAMPLES / "room48.ptu"), "--map",
                     str(SAMPLES / "room48_map.json"), "-o", str(out)]) == 0
    assert "4000 shots" in capsys.readouterr().out
    ref = room48_recording()
    r = read_recording(out)
    np.testing.assert_array_equal(r.bins, ref.bins)
    np.testing.assert_allclose(r.shot_time, ref.shot_time, rtol=0, atol=1e-15)
    m = load_map(SAMPLES / "room48_map.json")
    assert m.system is not None and m.system.receiver.image_size == (48, 1)


def test_cli_import_errors_are_one_line(tmp_path, capsys):
    mp = tmp_path / "m.json"
    mp.write_text(json.dumps({"format": "mems-stereo/tttr-map", "version": 1,
                              "pixels": [[0, 0, 0]],
                              "zero_crossings": {"source": "marker", "rising_edge": 1}}))
    rc = cli_main(["import", str(SAMPLES / "room48.ptu"), "--map", str(mp), "-o",
                   str(tmp_path / "o.h5")])
    err = capsys.readouterr().err
    assert rc == 2 and "system" in err and len(err.strip().splitlines()) == 1
    rc = cli_main(["import", str(SAMPLES / "room48.ptu"), "--map", str(SAMPLES / "room48_map.json"),
                   "-o", str(tmp_path / "o.h5"), "--all-photons"])
    assert rc == 2 and ".npz" in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_photon_hdf5_t3_like_round_trip(small_rec, tmp_path):
    """nanotimes + timestamps in laser periods: read like T3 (shot = timestamp)."""
    rec = small_rec
    period = 1.0 / rec.system.laser.f_rep
    origin = np.floor(min(rec.zero_crossings[0], 0.0) / period) * period
    k0 = int(round(-origin / period))
    k, p = np.nonzero(rec.bins.reshape(rec.n_shots, -1))
    code = rec.bins.reshape(rec.n_shots, -1)[k, p].astype(np.int64)
    zs = np.floor((rec.zero_crossings - origin) / period).astype(np.int64)
    ts = np.concatenate([k + k0, zs])
    det = np.concatenate([p, np.where(rec.rising > 0, 50, 51)])
    nt = np.concatenate([code - 1, np.zeros(zs.size, np.int64)])
    o = np.argsort(ts, kind="stable")
    write_photon_hdf5_events(tmp_path / "t3.h5", ts[o], det[o], timestamps_unit=period,
                             nanotimes=nt[o], tcspc_unit=rec.system.tdc.bin_width,
                             tcspc_num_bins=4096, laser_repetition_rate=rec.system.laser.f_rep)
    mp = {"format": "mems-stereo/tttr-map", "version": 1,
          "pixels": [[i, i, 0] for i in range(rec.bins.shape[2])],
          "zero_crossings": {"source": "channel", "rising_edge": 50, "falling_edge": 51},
          "shots": {"first": k0, "count": rec.n_shots}, "time_origin": float(origin)}
    info, blocks = photon_hdf5_stream(tmp_path / "t3.h5", block=333)
    assert info.mode == "T3" and info.micro_unit == rec.system.tdc.bin_width
    events_to_recording(blocks, info, map_from_dict(mp), rec.system, tmp_path / "o.h5")
    r2 = read_recording(tmp_path / "o.h5")
    np.testing.assert_array_equal(r2.bins, rec.bins)
    np.testing.assert_allclose(r2.shot_time, rec.shot_time, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(r2.rising, rec.rising)
