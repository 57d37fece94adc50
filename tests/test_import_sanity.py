"""Sanity of imports: a family of wrong maps generated from the bundled PTU sample's map.

Every wrong map (off-by-one clock, marker and pixel inputs, shifted pixels,
wrong binning and delay, swapped, wrong or missing markers, an inverted
polarity, reversed columns, a system of another mirror) is refused or warned
about with its cause named; the correct map and its equivalent variants
(one edge wired, markers swapped *and* polarity negative) import silently.
The import functions run in-process on the sample's events parsed once.
"""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import numpy as np
import pytest

from mems_stereo.cli import main as cli_main
from mems_stereo.cli._import_sanity import analyse_import
from mems_stereo.io import import_checks as ic
from mems_stereo.io.ptu import ptu_stream
from mems_stereo.io.tttr_map import map_from_dict
from mems_stereo.model.system import load_system, system_to_dict

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
PTU = SAMPLES / "room48.ptu"
MAP = SAMPLES / "room48_map.json"
N_PIX = 48


@pytest.fixture(scope="module")
def stream():
    """The sample's header info and its event blocks, decoded once."""
    info, open_blocks = ptu_stream(PTU)
    blocks = list(open_blocks())
    return info, lambda: iter(blocks)


@pytest.fixture(scope="module")
def base_map() -> dict:
    return json.loads(MAP.read_text())


def _analyse(stream, d: dict):
    info, blocks = stream
    m = map_from_dict(d, "case.json", SAMPLES)
    return analyse_import(blocks, info, m, m.system, 2.0)


def _edit(base: dict, path: str, value) -> dict:
    d = copy.deepcopy(base)
    *head, last = path.split(".")
    node = d
    for k in head:
        node = node[k]
    node[last] = value
    return d


def _pixels(base: dict, fn) -> dict:
    """The map with ``pixels`` rows ``fn(channel, column, row)`` (None drops a row)."""
    d = copy.deepcopy(base)
    d["pixels"] = [r for r in (fn(*p) for p in base["pixels"]) if r is not None]
    return d


def _system_with(base: dict, **scanner) -> dict:
    s = system_to_dict(load_system(SAMPLES / base["system"]))
    s["scanner"].update(scanner)
    return _edit(base, "system", s)


def wrong_maps(base: dict) -> list[tuple[str, dict, set]]:
    """(name, map, causes of which at least one must be named), generated from the
    sample's map."""
    C = ic
    cases = []
    for ch in (0, 1, 2, 3, 10, 23, 46, 47):  # the laser trigger on a pixel's input
        cases.append((f"clock on input {ch}", _edit(base, "shot_clock",
                                                    {"source": "channel", "channel": ch}),
                      {C.CAUSE_CLOCK_ON_PIXEL}))
    for ch in (48, 60):  # on an input without events
        cases.append((f"clock on idle input {ch}", _edit(base, "shot_clock",
                                                         {"source": "channel", "channel": ch}),
                      {C.CAUSE_IMPORT}))
    silent = {C.CAUSE_EDGE_SILENT, C.CAUSE_IMPORT}
    for r, f, causes in [(2, 3, silent), (3, 4, silent), (1, 3, silent), (3, 2, silent),
                         (3, 1, silent), (4, 2, silent), (1, 4, silent), (4, 3, silent),
                         (1, 1, {C.CAUSE_SAME_EDGE}), (2, 2, {C.CAUSE_SAME_EDGE}),
                         (2, 1, {C.CAUSE_POLARITY}), (2, None, {C.CAUSE_POLARITY}),
                         (None, 1, {C.CAUSE_POLARITY}), (None, 3, silent), (3, None, silent),
                         (None, 4, silent)]:
        zc = dict(base["zero_crossings"], rising_edge=r, falling_edge=f)
        cases.append((f"markers {r}/{f}", _edit(base, "zero_crossings", zc), causes))
    cases.append(("polarity negative", _edit(base, "zero_crossings.polarity", "negative"),
                  {C.CAUSE_POLARITY}))
    for k in (1, 2, 3, 4, 5, 8, 12, -1, -2, -3, -4, -5, -8):  # inputs off by k
        cases.append((f"pixel inputs {k:+d}",
                      _pixels(base, lambda c, u, v, k=k: [c + k, u, v] if c + k >= 0 else None),
                      {C.CAUSE_PIXELS_SHIFTED}))
    cases.append(("half the pixels mapped", _pixels(base, lambda c, u, v: [c, u, v]
                                                    if c < N_PIX // 2 else None),
                  {C.CAUSE_PIXELS_SHIFTED}))
    cases.append(("columns reversed", _pixels(base, lambda c, u, v: [c, N_PIX - 1 - u, v]),
                  {C.CAUSE_REVERSED}))
    for k in (1, 3):  # columns shifted off the sensor
        cases.append((f"columns {k:+d}", _pixels(base, lambda c, u, v, k=k: [c, u + k, v]),
                      {C.CAUSE_IMPORT}))
    for b in (1, 2, 4, 16, 32, 128):
        cases.append((f"binning {b}", _edit(base, "tdc.binning", b),
                      {C.CAUSE_BINNING, C.CAUSE_FEW_KEPT}))
    for db in (5000, -5000, 100000):
        cases.append((f"delay_bins {db}", _edit(base, "tdc.delay_bins", db),
                      {C.CAUSE_FEW_KEPT}))
    for pair in ((0, 1), (5, 6), (46, 47)):  # the monitor on pixel inputs
        zc = dict(base["zero_crossings"], source="channel", rising_edge=pair[0],
                  falling_edge=pair[1])
        cases.append((f"monitor on inputs {pair}", _edit(base, "zero_crossings", zc),
                      {C.CAUSE_CLOCK_ON_PIXEL}))
    zc = dict(base["zero_crossings"], source="channel", rising_edge=50, falling_edge=51)
    cases.append(("monitor on idle inputs", _edit(base, "zero_crossings", zc),
                  {C.CAUSE_EDGE_SILENT, C.CAUSE_IMPORT}))
    f_mech = load_system(SAMPLES / base["system"]).scanner.f_mech
    for factor in (0.5, 2.0, 1.5):  # a system of another mirror
        cases.append((f"f_mech x{factor}", _system_with(base, f_mech=f_mech * factor),
                      {C.CAUSE_ZC_RATE}))
    return cases


def correct_maps(base: dict) -> list[tuple[str, dict]]:
    """Maps that describe the sample's wiring correctly."""
    zc = base["zero_crossings"]
    return [("the sample's map", base),
            ("rising edge only", _edit(base, "zero_crossings", dict(zc, falling_edge=None))),
            ("falling edge only", _edit(base, "zero_crossings", dict(zc, rising_edge=None))),
            ("markers swapped, polarity negative", _edit(base, "zero_crossings", dict(
                zc, rising_edge=2, falling_edge=1, polarity="negative"))),
            ("a selection of shots", _edit(base, "shots", {"first": 2500, "count": 1000})),
            ("pixels as objects", _pixels(base, lambda c, u, v: {"channel": c, "column": u,
                                                                 "row": v}))]


#: the families of wrong maps, by the first word of their names
GROUPS = {"clock": ("clock",), "markers": ("markers", "polarity"),
          "pixels": ("pixel", "half", "columns"), "tdc": ("binning", "delay_bins"),
          "monitor": ("monitor", "f_mech")}


def test_the_family_has_at_least_50_wrong_maps(base_map):
    cases = wrong_maps(base_map)
    grouped = [c for c in cases if any(c[0].startswith(p) for ps in GROUPS.values()
                                       for p in ps)]
    print(f"{len(cases)} wrong maps generated from {MAP.name}")
    assert len(cases) >= 50 and len(grouped) == len(cases)
    assert len({c[0] for c in cases}) == len(cases)


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_every_wrong_map_is_refused_or_warned_with_its_cause(stream, base_map, group):
    cases = [c for c in wrong_maps(base_map) if c[0].startswith(GROUPS[group])]
    missed = []
    for name, d, causes in cases:
        res = _analyse(stream, d)
        named = {v.cause for v in res.verdicts}
        if not named & causes:
            missed.append(f"{name}: expected {sorted(causes)}, got "
                          f"{[v.line() for v in res.verdicts]}")
        for v in res.verdicts:  # each names a map field and says what to do
            assert v.field and v.text and v.cause
    print(f"{group}: {len(cases) - len(missed)} of {len(cases)} wrong maps refused or warned "
          f"with their cause named")
    assert cases and not missed, "\n".join(missed)


def test_correct_maps_import_silently(stream, base_map):
    for name, d in correct_maps(base_map):
        res = _analyse(stream, d)
        assert res.verdicts == [], (name, [v.line() for v in res.verdicts])
        s = res.sample
        assert s.kept == s.stats.photons == 23904  # the selection of shots is not checked
        assert abs(s.shots_per_s / s.sync_rate - 1) < 1e-9
        assert s.polarity.z < -3 and s.reversed_columns.z < -3


def test_sample_statistics_against_the_events(stream, base_map):
    """The statistics agree with counts made here from the raw events."""
    info, blocks = stream
    ev = list(blocks())
    kind = np.concatenate([b.kind for b in ev])
    chan = np.concatenate([b.channel for b in ev])
    res = _analyse(stream, base_map)
    s = res.sample
    assert s.events.syncs == int((kind == 1).sum()) == s.n_shots == 4000
    assert sum(s.events.photons.values()) == int((kind == 0).sum()) == s.stats.photons
    assert s.events.markers == {1: int(((kind == 2) & (chan == 1)).sum()),
                                2: int(((kind == 2) & (chan == 2)).sum())}
    assert s.n_zero_crossings == s.events.markers[1] + s.events.markers[2]
    # 2 f_mech within the scan's own drift: the sample was simulated at f_mech
    assert abs(s.zc_per_s / (2 * s.f_mech) - 1) < 0.01
    cut = ic.first_seconds(blocks, info, 0.05)
    n_cut = sum(len(b) for b in cut())
    t = np.concatenate([b.macro for b in ev]) * info.macro_unit
    assert n_cut == int((t < t[0] + 0.05).sum())


def test_pure_checks_thresholds():
    """The rate checks at their limits, on hand-made statistics."""
    from mems_stereo.io.tttr import ImportStats
    from mems_stereo.io.tttr_map import TttrMap

    m = TttrMap(np.array([[0, 0, 0], [1, 1, 0]]))

    def sample(shots_per_s, zc_per_s):
        return ic.ImportSample(1.0, 1001, 1000 / shots_per_s, 20000.0, 20000.0, 101,
                               100 / zc_per_s, 1000.0, ImportStats(photons=100),
                               ic.EventCounts({0: 50, 1: 50}, {1: 50, 2: 51}, 1001), 1e-12,
                               64e-12)
    assert ic.rate_verdicts(sample(20000.0, 2000.0), m) == []
    v = ic.rate_verdicts(sample(20000 * 1.05, 2000.0), m)
    assert [(x.refuse, x.cause) for x in v] == [(False, ic.CAUSE_SHOT_RATE)]
    v = ic.rate_verdicts(sample(20000 * 1.2, 2000 * 1.2), m)
    assert [(x.refuse, x.cause) for x in v] == [(True, ic.CAUSE_SHOT_RATE),
                                                (False, ic.CAUSE_ZC_RATE)]
    v = ic.rate_verdicts(sample(20000.0, 1000.0), m)
    assert [(x.refuse, x.field) for x in v] == [(True, "zero_crossings")]
    assert "2000" in v[0].text and "1000" in v[0].text


def _cli(tmp_path, capsys, d: dict | None, *extra):
    mp = tmp_path / "map.json"
    if d is not None:
        d = dict(d, system=str(SAMPLES / d["system"]))
    mp.write_text(json.dumps(d))
    rc = cli_main(["import", str(PTU), "--map", str(mp), *extra])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_refuses_warns_and_dry_runs(tmp_path, capsys, base_map):
    rc, out, err = _cli(tmp_path, capsys, base_map, "-o", str(tmp_path / "ok.h5"))
    assert rc == 0 and err == "" and (tmp_path / "ok.h5").exists()
    clock = _edit(base_map, "shot_clock", {"source": "channel", "channel": 3})
    rc, out, err = _cli(tmp_path, capsys, clock, "-o", str(tmp_path / "c.h5"))
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "shot_clock.channel" in err and "pixels[3]" in err
    assert not (tmp_path / "c.h5").exists()
    shifted = _pixels(base_map, lambda c, u, v: [c + 3, u, v])
    rc, out, err = _cli(tmp_path, capsys, shifted, "-o", str(tmp_path / "s.h5"))
    assert rc == 0 and "warning" in err and "pixels" in err and "subtract 3" in err
    before = sorted(tmp_path.iterdir())
    rc, out, err = _cli(tmp_path, capsys, base_map, "--dry-run", "--dry-run-seconds", "0.1")
    assert rc == 0 and err == "" and "verdict: clean" in out
    assert re.search(r"first 0.1 s read: 19\d\d shots over 0.09\d+ s, 20000 shots/s \(header sync rate 20000 Hz\)",
                     out)
    swapped = _edit(base_map, "zero_crossings", dict(base_map["zero_crossings"],
                                                     rising_edge=2, falling_edge=1))
    rc, out, err = _cli(tmp_path, capsys, swapped, "--dry-run")
    assert rc == 2 and "zero_crossings.polarity" in err and "'negative'" in err
    assert "refused (polarity inverted)" in out
    assert sorted(tmp_path.iterdir()) == before  # the dry runs wrote nothing
    rc, out, err = _cli(tmp_path, capsys, base_map)
    assert rc == 2 and "--output" in err


def test_t3_marker_monitor_is_warned_not_refused(stream, base_map, tmp_path):
    """The sample re-encoded as T3 (the monitor on markers, quantised to the sync
    period): a warning naming zero_crossings.source, and the geometric evidence,
    off by the quantisation, only warned."""
    from mems_stereo.io.ptu import recording_to_ptu
    from mems_stereo.io.recording import read_recording
    from mems_stereo.io.tttr import events_to_recording

    info, blocks = stream
    m = map_from_dict(base_map, "m.json", SAMPLES)
    events_to_recording(blocks, info, m, m.system, tmp_path / "r.h5")
    d = recording_to_ptu(read_recording(tmp_path / "r.h5"), tmp_path / "r3.ptu", mode="T3")
    d["system"] = base_map["system"]
    info3, open3 = ptu_stream(tmp_path / "r3.ptu")
    m3 = map_from_dict(d, "m3.json", SAMPLES)
    res = analyse_import(open3, info3, m3, m3.system, 2.0)
    assert not res.refusals
    t3 = [v for v in res.verdicts if v.cause == ic.CAUSE_T3_MARKER]
    assert len(t3) == 1 and t3[0].field == "zero_crossings.source"
    assert "5e-05 s" in t3[0].text and "8 %" in t3[0].text  # 50 µs × 1570 Hz


def test_photon_hdf5_wiring_is_checked_the_same(stream, base_map, tmp_path):
    """The sample as Photon-HDF5 (no markers, no sync events: the laser trigger on
    detector 60, the monitor's edges on detectors 61 and 62): silent when mapped
    right; the trigger on a pixel's detector refused; no sync rate in the file, so
    the shots are compared with the system's laser.f_rep."""
    from mems_stereo.io.photon_hdf5 import photon_hdf5_stream, write_photon_hdf5_events

    info, blocks = stream
    ev = list(blocks())
    t = np.concatenate([b.macro for b in ev])
    kind = np.concatenate([b.kind for b in ev])
    ch = np.concatenate([b.channel for b in ev]).astype(np.int64)
    det = np.where(kind == 1, 60, np.where(kind == 2, 60 + ch, ch))
    write_photon_hdf5_events(tmp_path / "p.h5", t, det, timestamps_unit=info.macro_unit)
    info_h, open_h = photon_hdf5_stream(tmp_path / "p.h5")
    d = dict(copy.deepcopy(base_map), shot_clock={"source": "channel", "channel": 60})
    d["zero_crossings"] = dict(d["zero_crossings"], source="channel", rising_edge=61,
                               falling_edge=62)
    res = analyse_import(open_h, info_h, *_map_system(d), 2.0)
    assert res.verdicts == [], [v.line() for v in res.verdicts]
    assert info_h.sync_rate == 0 and abs(res.sample.shots_per_s - 20000) < 1e-6
    d["shot_clock"]["channel"] = 7
    res = analyse_import(open_h, info_h, *_map_system(d), 2.0)
    assert [v.field for v in res.refusals][:2] == ["shot_clock.channel", "shot_clock"]
    assert "laser.f_rep" in res.refusals[1].text


def _map_system(d: dict):
    m = map_from_dict(d, "m.json", SAMPLES)
    return m, m.system


def test_pure_shift_and_dead_pixel():
    """Active unmapped and silent mapped inputs: the shift that explains both, or a dead pixel."""
    from mems_stereo.io.tttr import ImportStats
    from mems_stereo.io.tttr_map import TttrMap

    m = TttrMap(np.array([[0, 0, 0], [1, 1, 0], [2, 2, 0]]))

    def verdicts(photons: dict):
        s = ic.ImportSample(1.0, 1001, 0.05, 20000.0, 20000.0, 101, 0.05, 1000.0,
                            ImportStats(photons=sum(photons.values())),
                            ic.EventCounts(photons, {1: 50, 2: 51}, 1001), 1e-12, 64e-12)
        return [v for v in ic.photon_verdicts(s, m) if v.cause == ic.CAUSE_PIXELS_SHIFTED]

    assert verdicts({0: 100, 1: 100, 2: 100, 7: 5}) == []  # 5 % of a pixel: cross-talk
    v = verdicts({0: 100, 1: 100})
    assert len(v) == 1 and "mapped input 2 has (almost) none: dead pixels" in v[0].text
    v = verdicts({1: 100, 2: 100, 3: 100})  # wired one input up: channel c is pixel c - 1
    assert len(v) == 1 and not v[0].refuse and "add 1 to each pixel's channel" in v[0].text
    assert "input 3 carries 100 photons but no pixel; mapped input 0 has" in v[0].text
