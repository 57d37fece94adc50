"""Field-level fuzz: every member of every JSON file kind, and the inputs that once
reached an ``internal error``.

* Every member present in a valid example of each JSON kind (system: one-axis,
  calibrated, two-axis; TTTR map; target distances; scene) is given a value of
  a wrong JSON type, and each positive quantity a negative and a zero value;
  ``format`` and ``version`` a wrong one.  Each file goes through the command
  that reads it; the run must end with exit 2 and one line that names the file
  and the dotted field (tests/test_fuzz.py's rules: no traceback, no
  ``internal error``, nothing written).
* The catalogue's gaps: labels outside 0..2, shot times ten laser periods apart,
  a ``--system`` whose TDC has fewer codes than the recording uses (calibrate,
  process two-axis, simulate, info, plot), a zero baseline, a cloud without the
  attribute to colour by, histogram files of the wrong version or counts, and a
  ``--system`` path with a typo (through every command that takes one).

Runs in-process (:func:`mems_stereo.cli.main`), so the cases are fast.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from fuzz_cases import SAMPLES, h5mut, write_json
from test_fuzz import check_refused, run_cli

from mems_stereo.util.jsonfile import Field
from mems_stereo.util.schemas import SCHEMAS

DATA = Path(__file__).resolve().parent / "data"

#: one value of each JSON type, and the types (Field.type words) that accept it
JSON_VALUES = [("x", {"string"}), (1.5, {"number"}), (True, {"boolean"}),
               ([], {"array"}), ({}, {"object"}), (None, {"null"}),
               (7, {"integer", "number"})]


def wrong_types(f: Field, k: int) -> list:
    """Two values of JSON types ``f`` does not accept (chosen by the leaf's number
    ``k``, so that every type is used across the leaves)."""
    accepted = set(f.type.split("|"))
    bad = [v for v, types in JSON_VALUES if not types & accepted]
    return [bad[k % len(bad)], bad[(k + 3) % len(bad)]] if len(bad) > 1 else bad


def leaves(d, fields: dict, path=()):
    """``(path, Field)`` of every member present in the example ``d`` (objects are
    entered; of a list of objects and of a name-keyed object only the first)."""
    for key, v in d.items():
        f = fields.get(key)
        if f is None:
            continue
        yield path + (key,), f
        yield from _inner(v, f, path + (key,))


def _inner(v, f: Field, path):
    if isinstance(v, dict):
        if f.variants is not None:
            yield from leaves(v, f.variants[1][v[f.variants[0]]], path)
        elif f.fields is not None:
            yield from leaves(v, f.fields, path)
        elif f.values is not None and v:
            first = next(iter(v))
            yield path + (first,), f.values
            yield from _inner(v[first], f.values, path + (first,))
    elif isinstance(v, list) and v and f.items is not None and isinstance(v[0], dict):
        yield path + (0,), f.items
        yield from _inner(v[0], f.items, path + (0,))


def dotted(path) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def _set(d, path, value):
    d = copy.deepcopy(d)
    node = d
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return d


def mutations(valid: dict, kind: str):
    """``(name, mutated dict, dotted field)``: wrong types of every member, negative
    and zero positive quantities, a wrong format and version."""
    out = [("format", _set(valid, ("format",), "mems-stereo/other"), "format"),
           ("version-99", _set(valid, ("version",), 99), "version"),
           ("version-str", _set(valid, ("version",), "1"), "version")]
    for k, (path, f) in enumerate(leaves(valid, SCHEMAS[kind])):
        if path[-1] in ("format", "version"):
            continue
        bad = wrong_types(f, k)
        if f.expect == "a positive number":
            bad += [-1.0, 0]
        for v in bad:
            out.append((f"{dotted(path)}={json.dumps(v)}", _set(valid, path, v), dotted(path)))
    return out


def _read(p: Path) -> dict:
    return json.loads(p.read_text())


def _copy_system(d: Path):
    shutil.copy(SAMPLES / "room48_system.json", d / "room48_system.json")


#: kind → (examples, file name, command line ({d}: the case's folder, {s}: samples/))
KINDS = {
    "system": ([_read(SAMPLES / "nominal_system.json"), _read(DATA / "calibrated_system.json"),
                _read(SAMPLES / "raster128x96_system.json")], "s.json",
               ["info", "--system", "{d}/s.json"]),
    "tttr-map": ([_read(SAMPLES / "room48_map.json")], "map.json",
                 ["import", "{s}/room48.ptu", "--map", "{d}/map.json", "-o", "{d}/o.h5"]),
    "target-distances": ([_read(SAMPLES / "calib_distances.json")], "dist.json",
                         ["calibrate", "{s}/calib_1.5m.h5", "{s}/calib_2.5m.h5", "-o",
                          "{d}/c.json", "--target-distances-file", "{d}/dist.json"]),
    "scene": ([_read(SAMPLES / "room_scene.json")], "scene.json",
              ["simulate", "{d}/scene.json", "-o", "{d}/o.h5", "--shots", "10"]),
}


def _field_cases():
    cases, seen = [], set()
    for kind, (examples, fname, argv) in KINDS.items():
        for valid in examples:
            for name, d, fld in mutations(valid, kind):
                cid = f"{kind}-{name}"
                if cid in seen:  # the examples share members: each mutation once
                    continue
                seen.add(cid)
                build = write_json(fname, d)
                if kind == "tttr-map":
                    build = (lambda b: lambda t: (b(t), _copy_system(t)))(build)
                cases.append((cid, build, argv, f"{fname}: {fld}"))
    return cases


FIELD_CASES = _field_cases()


def test_field_case_count():
    """Every kind, every member of the examples: a few hundred cases."""
    kinds = {c[0].split("-")[0] for c in FIELD_CASES}
    assert {"system", "tttr", "target", "scene"} <= kinds
    assert len(FIELD_CASES) >= 200, len(FIELD_CASES)
    print(f"\nfield fuzz: {len(FIELD_CASES)} cases")


@pytest.mark.parametrize("case", FIELD_CASES, ids=[c[0] for c in FIELD_CASES])
def test_field_refused(case, tmp_path):
    _, build, argv, expect = case
    build(tmp_path)
    check_refused(tmp_path, argv, expect)


# ------------------------------------------------------- the catalogue's gaps

def _labels(value, dtype=np.uint8, src="room.h5"):
    def m(f, d):
        a = f["truth/label"][()].astype(dtype)
        a.flat[int(np.flatnonzero(a.reshape(-1) == 1)[0])] = value
        del f["truth/label"]
        f["truth/label"] = a
    return h5mut(m, src)


def _stride(factor, src="room.h5"):
    def m(f, d):
        t = f["shots/time"][()]
        f["shots/time"][...] = t[0] + (t - t[0]) * factor
    return h5mut(m, src)


def _system_file(change, src="nominal_system.json", name="s.json"):
    def b(d: Path):
        s = _read(SAMPLES / src)
        change(s)
        (d / name).write_text(json.dumps(s))
    return b


def _bins(n):
    return lambda s: s["tdc"].__setitem__("n_bins", n)


def _zero_baseline(s):
    s["scanner"]["position"] = [0.0, 0.0, 0.0]


def _ply_without_range(d: Path):
    n = 50
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {n}",
            "property double x", "property double y", "property double z", "end_header"]
    body = np.random.default_rng(3).normal(size=(n, 3)).astype("<f8").tobytes()
    (d / "c.ply").write_bytes(("\n".join(head) + "\n").encode() + body)


def _hist(mutate):
    def b(d: Path):
        from mems_stereo.io.histograms import write_histograms

        a = np.ones((1, 8, 16), np.int32)
        write_histograms(d / "h.h5", a, a, a)
        with h5py.File(d / "h.h5", "r+") as f:
            mutate(f)
    return b


def _dataset(name, value):
    def m(f):
        del f[name]
        f[name] = value
    return m


PROC = ["process", "{d}/m.h5", "-o", "{d}/o.ply"]
PROC2 = ["process", "{d}/m.h5", "-o", "{d}/o.ply"]
CAL = ["calibrate", "{s}/calib_1.5m.h5", "{s}/calib_2.5m.h5", "-o", "{d}/c.json"]
CAL2 = ["calibrate", "{s}/lissajous64_calib_1.5m.h5", "{s}/lissajous64_calib_2.5m.h5", "-o",
        "{d}/c.json"]
SIM = ["simulate", "{s}/room_scene.json", "-o", "{d}/o.h5", "--shots", "10"]
GAPS = [
    ("labels-7", _labels(7), PROC, "m.h5: /truth/label: expected labels 0"),
    ("labels-255", _labels(255), PROC, "m.h5: /truth/label"),
    ("labels-negative", _labels(-1, np.int8), PROC, "m.h5: /truth/label"),
    ("labels-7-two-axis", _labels(7, src="lissajous64.h5"), PROC2, "m.h5: /truth/label"),
    ("stride-10", _stride(10.0), PROC, "m.h5: /shots/time: the median shot interval"),
    ("stride-0.1", _stride(0.1), PROC, "m.h5: /shots/time"),
    ("stride-10-calibrate", _stride(10.0, "calib_2.5m.h5"),
     ["calibrate", "{s}/calib_1.5m.h5", "{d}/m.h5", "-o", "{d}/c.json"], "m.h5: /shots/time"),
    ("stride-10-two-axis", _stride(10.0, "lissajous64.h5"), PROC2, "m.h5: /shots/time"),
    ("codes-calibrate", _system_file(_bins(64)), CAL + ["--system", "{d}/s.json"],
     "calib_1.5m.h5: /shots/bins: expected codes 0..64"),
    ("codes-calibrate-two-axis", _system_file(_bins(16), "lissajous64_system.json"),
     CAL2 + ["--system", "{d}/s.json"], "/events/code: expected codes 0..16"),
    ("codes-process-two-axis", _system_file(_bins(16), "lissajous64_system.json"),
     ["process", "{s}/lissajous64.h5", "-o", "{d}/o.ply", "--system", "{d}/s.json"],
     "lissajous64.h5: /events/code"),
    ("codes-simulate", _system_file(_bins(64)),
     SIM + ["--system", "{d}/s.json", "--true-system", "{s}/calib_true_system.json"],
     "s.json: tdc.n_bins: 64 codes, fewer than the 4096"),
    ("codes-info", _system_file(_bins(16)), ["info", "--system", "{d}/s.json"],
     "s.json: tdc.n_bins: 16 codes of 312.5 ps reach"),
    ("codes-plot", _system_file(_bins(16)),
     ["plot", "acquisition", "-o", "{d}/a.png", "--system", "{d}/s.json"], "s.json: tdc.n_bins"),
    ("zero-baseline-info", _system_file(_zero_baseline), ["info", "--system", "{d}/s.json"],
     "s.json: scanner.position: expected the mirror away"),
    ("zero-baseline-process", _system_file(_zero_baseline),
     ["process", "{s}/room.h5", "-o", "{d}/o.ply", "--system", "{d}/s.json"],
     "s.json: scanner.position"),
    ("zero-baseline-simulate", _system_file(_zero_baseline), SIM + ["--system", "{d}/s.json"],
     "s.json: scanner.position"),
    ("cloud-no-range-plot", _ply_without_range, ["plot", "cloud", "{d}/c.ply", "-o", "{d}/t.png"],
     "c.ply: no attribute 'range' to colour by"),
    ("cloud-no-range-render", _ply_without_range, ["render", "{d}/c.ply", "-o", "{d}/t.png"],
     "c.ply: no attribute 'range'"),
    ("cloud-no-range-view", _ply_without_range, ["view", "{d}/c.ply"], "c.ply: no attribute"),
    ("cloud-no-attribute", _ply_without_range,
     ["plot", "cloud", "{d}/c.ply", "-o", "{d}/t.png", "--color-by", "counts"],
     "c.ply: no attribute 'counts'"),
    ("hist-version-99", _hist(lambda f: f.attrs.__setitem__("version", 99)),
     ["plot", "histograms", "{d}/h.h5", "-o", "{d}/t.png"], "h.h5"),
    ("hist-format-other", _hist(lambda f: f.attrs.__setitem__("format", "mems-stereo/labels")),
     ["plot", "histograms", "{d}/h.h5", "-o", "{d}/t.png"], "h.h5"),
    ("hist-counts-int64", _hist(_dataset("raw", np.full((1, 8, 16), 1 << 40, np.int64))),
     ["plot", "histograms", "{d}/h.h5", "-o", "{d}/t.png"], "h.h5: /raw"),
    ("hist-counts-string", _hist(_dataset("signal", np.full((1, 8, 16), b"x"))),
     ["plot", "histograms", "{d}/h.h5", "-o", "{d}/t.png"], "h.h5: /signal"),
]

def _map_system(name):
    def b(d: Path):
        m = _read(SAMPLES / "room48_map.json")
        m["system"] = name
        (d / "map.json").write_text(json.dumps(m))
        _copy_system(d)
    return b


IMPORT = ["import", "{s}/room48.ptu", "--map", "{d}/map.json", "-o", "{d}/o.h5"]
GAPS += [("map-system-typo", _map_system("room48_sytem.json"), IMPORT,
          "map.json: system: {d}/room48_sytem.json: not found"),
         ("map-system-no-preset", _map_system("burkard2021"), IMPORT,
          "map.json: system: unknown preset 'burkard2021'")]

# empty file names (they would mean the working folder): refused naming the argument
GAPS += [(f"empty-{'-'.join(a for a in argv[:2] if a and not a.startswith('{'))}-{k}",
          _ply_without_range, argv, expect) for k, (argv, expect) in enumerate([
              (["process", "", "-o", "{d}/o.ply"], "recordings: expected a file name"),
              (["process", "{s}/room.h5", "-o", ""], "--output: expected a file name"),
              (["process", "{s}/room.h5", "-o", "{d}/o.ply", "--labels", ""], "--labels:"),
              (CAL + ["--target-distances-file", ""], "--target-distances-file: expected"),
              (["simulate", "", "-o", "{d}/o.h5"], "scene: expected a file name"),
              (["plot", "cloud", "", "-o", "{d}/t.png"], "cloud: expected a file name"),
              (["render", "{d}/c.ply", "-o", ""], "--output: expected a file name"),
              (["export", "", "-o", "{d}/e.las"], "cloud: expected a file name"),
              (["import", "", "--map", "{s}/room48_map.json", "-o", "{d}/o.h5"],
               "input: expected a file name"),
              (["info", "--plot", ""], "--plot: expected a file name")])]

#: every command that takes --system, with a typo'd path: "FILE: not found"
SYSTEM_ARGV = {
    "info": ["info"], "simulate": SIM, "plot": ["plot", "acquisition", "-o", "{d}/a.png"],
    "process": ["process", "{s}/room.h5", "-o", "{d}/o.ply"], "calibrate": CAL,
    "render": ["render", "{d}/c.ply", "-o", "{d}/t.png"],
    "import": ["import", "{s}/room48.ptu", "--map", "{s}/room48_map.json", "-o", "{d}/o.h5"],
}
for _cmd, _argv in SYSTEM_ARGV.items():
    GAPS.append((f"system-typo-{_cmd}",
                 (lambda d: (_system_file(lambda s: None, name="calibrated.json")(d),
                             _ply_without_range(d))),
                 _argv + ["--system", "{d}/calibratd.json"],
                 "--system: {d}/calibratd.json: not found"))
    GAPS.append((f"system-no-preset-{_cmd}", _ply_without_range,
                 _argv + ["--system", "lisajous64"], "--system: unknown preset 'lisajous64'"))
    GAPS.append((f"system-empty-{_cmd}", _ply_without_range, _argv + ["--system", ""],
                 "--system: expected a system JSON file or a preset, found an empty name"))


@pytest.mark.parametrize("name, build, argv, expect", GAPS, ids=[g[0] for g in GAPS])
def test_gap_refused(name, build, argv, expect, tmp_path):
    build(tmp_path)
    check_refused(tmp_path, argv, expect.replace("{d}", str(tmp_path)))


def test_system_typo_advice(tmp_path):
    """The advice line names the nearby file, or the preset meant."""
    (tmp_path / "calibrated.json").write_text((SAMPLES / "nominal_system.json").read_text())
    rc, err, _ = run_cli(["info", "--system", f"{tmp_path}/calibratd.json"])
    assert rc == 2 and err.splitlines()[1] == f"  did you mean {tmp_path}/calibrated.json?"
    rc, err, _ = run_cli(["info", "--system", "lisajous64"])
    assert rc == 2 and "did you mean 'lissajous64'?" in err.splitlines()[1]
    rc, err, _ = run_cli(["info", "--system", f"{tmp_path}/lissajous64.json"])
    assert rc == 2 and "did you mean the preset 'lissajous64'" in err.splitlines()[1]


def test_option_of_another_command_advice():
    """An option of another command is named as such, never "--x (not --x)"."""
    rc, err, _ = run_cli(["info", "--confidence", "0.5"])
    assert rc == 2 and "(not --confidence)" not in err
    assert err.splitlines()[1] == "  --confidence is an option of process and live, not of info"
    rc, err, _ = run_cli(["info", "--confidenc", "0.5"])
    assert "did you mean --confidence (an option of process and live, not of info)?" in err
    rc, err, _ = run_cli(["plot", "cloud", "c.ply", "-o", "t.png", "--colour-by", "z"])
    assert rc == 2 and "did you mean --color-by (not --colour-by)?" in err


def test_every_preset_resolves_in_the_cli_and_the_api(tmp_path):
    """One registry: every preset of ``ms.PRESETS`` passes the --system check every
    command shares (run through ``info``, whose only input is the system) and
    ``ms.preset``; the --system path check of the commands is one function (the
    typo cases above run it through each command)."""
    import mems_stereo as ms
    from mems_stereo.model.presets import TWO_AXIS_PRESETS

    assert set(TWO_AXIS_PRESETS) < set(ms.PRESETS) and "burkard2022" in ms.PRESETS
    for name in ms.PRESETS:
        rc, err, out = run_cli(["info", "--system", name])
        assert rc == 0, err
        assert out.startswith(f"system: {name}")
        assert ms.preset(name).tdc.n_bins == ms.PRESETS[name]().tdc.n_bins
