"""Strict schemas of every JSON file kind the package reads (issue 32).

The mutation test: every key of a valid example of each kind (bundled
samples, a calibrated one-axis and a two-axis system written by
``mems-stereo calibrate``) is mistyped by one character (each deletion, each
transposition of neighbours, a substitution by a keyboard neighbour at each
position); every such file is refused with a did-you-mean naming the key.
The schema-wide mutation test does the same for every key every schema declares
(also those absent from the examples), against the schema check directly: every
deletion and transposition, and at each position a seeded sample of insertions
and substitutions (count printed; 100 % required); a few typos go through the CLI.
Also: unknown keys refused, wrong types refused with the field named, every
valid file loads, and ``docs/formats.md`` lists exactly the declared members.
"""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import pytest

from mems_stereo.errors import FormatError
from mems_stereo.io.tttr_map import map_from_dict
from mems_stereo.model.system import system_from_dict
from mems_stereo.sim.scene import scene_from_dict
from mems_stereo.util.jsonfile import Field, closest_key, read_json_file
from mems_stereo.util.schemas import SCHEMAS, schema_markdown, schema_rows

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "samples"
DATA = Path(__file__).resolve().parent / "data"

_ROWS = ["qwertyuiop", "asdfghjkl", "zxcvbnm", "1234567890"]


def _neighbour(c: str) -> str:
    """A keyboard neighbour of ``c`` (``_`` → ``-``)."""
    for row in _ROWS:
        i = row.find(c.lower())
        if i >= 0:
            return row[i + 1] if i + 1 < len(row) else row[i - 1]
    return "-"


def typos(key: str) -> list[str]:
    """Deterministic one-character typos: deletions, transpositions, substitutions."""
    out = [key[:i] + key[i + 1:] for i in range(len(key))]
    out += [key[:i] + key[i + 1] + key[i] + key[i + 2:] for i in range(len(key) - 1)]
    out += [key[:i] + _neighbour(key[i]) + key[i + 1:] for i in range(len(key))]
    seen, uniq = {key}, []
    for t in out:
        if t and t not in seen:
            seen.add(t)
            uniq.append(t)
    return uniq


def _distances_loader(tmp: Path):
    from calib.calibrate import read_target_distances

    def load(d):
        p = tmp / "distances.json"
        p.write_text(json.dumps(d))
        read_target_distances(p, ["calib_1.5m.h5"])
    return load


def examples(tmp: Path):
    """(name, kind, loader, valid dict) of every example."""
    def system(d):
        system_from_dict(d, "system.json")

    def the_map(d):
        map_from_dict(d, "map.json", SAMPLES)

    def scene(d):
        scene_from_dict(d, "scene.json", SAMPLES)

    rd = read_json_file
    return [
        ("nominal system", "system", system, rd(SAMPLES / "nominal_system.json")),
        ("true system (phase_offset)", "system", system, rd(SAMPLES / "calib_true_system.json")),
        ("calibrated system", "system", system, rd(DATA / "calibrated_system.json")),
        ("two-axis system", "system", system, rd(SAMPLES / "raster128x96_system.json")),
        ("calibrated two-axis system", "system", system,
         rd(DATA / "calibrated_twoaxis_system.json")),
        ("TTTR map", "tttr-map", the_map, rd(SAMPLES / "room48_map.json")),
        ("target distances", "target-distances", _distances_loader(tmp),
         rd(SAMPLES / "calib_distances.json")),
        ("scene", "scene", scene, rd(SAMPLES / "room_scene.json")),
    ]


def declared_objects(d, fields: dict, path=()):
    """(path to an object, its declared members) for every object the schema
    names members of (not the name-keyed ones, whose keys are data)."""
    yield path, fields
    for k, v in d.items():
        f = fields.get(k)
        if f is None:
            continue
        yield from _declared_value(v, f, path + (k,))


def _declared_value(v, f: Field, path):
    if isinstance(v, dict):
        if f.variants is not None:
            yield from declared_objects(v, f.variants[1][v[f.variants[0]]], path)
        elif f.fields is not None:
            yield from declared_objects(v, f.fields, path)
        elif f.values is not None and f.values.fields is not None:
            for k, x in v.items():
                yield from declared_objects(x, f.values.fields, path + (k,))
    elif isinstance(v, list) and f.items is not None:
        for i, x in enumerate(v[:2]):  # the first two elements of a list stand for all
            yield from _declared_value(x, f.items, path + (i,))


def _at(d, path):
    for p in path:
        d = d[p]
    return d


def _renamed(obj: dict, old: str, new: str) -> dict:
    return {(new if k == old else k): v for k, v in obj.items()}


def _renamed_at(d, path, old: str, new: str):
    """``d`` with the key ``old`` of the object at ``path`` renamed ``new``: the objects
    and lists on the path are copied, the rest shared (the loaders do not modify it)."""
    if not path:
        return _renamed(d, old, new)
    out = list(d) if isinstance(d, list) else dict(d)
    out[path[0]] = _renamed_at(d[path[0]], path[1:], old, new)
    return out


def test_mutation_every_key_typo_refused_with_did_you_mean(tmp_path, capsys):
    total, refused, skipped, keys = 0, 0, 0, 0
    failures = []
    for name, kind, load, valid in examples(tmp_path):
        load(copy.deepcopy(valid))  # the example itself is valid
        for path, fields in declared_objects(valid, SCHEMAS[kind]):
            obj = _at(valid, path)
            for key in list(obj):
                keys += 1
                for typo in typos(key):
                    if typo in obj or typo in fields:  # another valid key: not a typo
                        skipped += 1
                        continue
                    d = _renamed_at(valid, path, key, typo)
                    total += 1
                    try:
                        load(d)
                    except FormatError as e:
                        if f"did you mean {key}?" in str(e):
                            refused += 1
                            continue
                        failures.append(f"{name}: {'.'.join(map(str, path + (typo,)))}: {e}")
                    else:
                        failures.append(f"{name}: {'.'.join(map(str, path + (typo,)))}: "
                                        "accepted")
    with capsys.disabled():
        print(f"\nmutation test: {refused} of {total} one-character typos of {keys} keys "
              f"refused with the right did-you-mean ({100.0 * refused / total:.1f} %); "
              f"{skipped} typos that are other valid keys not counted")
    assert not failures, "\n".join(failures[:20])
    assert total > 1000 and refused == total


def test_typos_helper():
    assert typos("ab") == ["b", "a", "ba", "sb", "an"]
    assert closest_key("phase_ofset", ["theta0", "phase_offset"]) == "phase_offset"
    assert closest_key("zzz", ["theta0", "phase_offset"]) is None


def _load_system(d):
    return system_from_dict(d, "sys.json")


def test_issue_examples():
    d = read_json_file(SAMPLES / "nominal_system.json")
    d["scanner"]["phase_ofset"] = 0.01
    with pytest.raises(FormatError, match=r"^sys\.json: scanner\.phase_ofset: unknown field; "
                                          r"did you mean phase_offset\?$"):
        _load_system(d)
    d = read_json_file(SAMPLES / "nominal_system.json")
    d["scanner"]["theta_mech_maxx"] = d["scanner"].pop("theta_mech_max")
    with pytest.raises(FormatError, match=r"scanner\.theta_mech_max: required field is missing; "
                                          r"found theta_mech_maxx — did you mean theta_mech_max\?"):
        _load_system(d)


@pytest.mark.parametrize("where", [(), ("receiver",), ("scanner",), ("laser",), ("tdc",),
                                   ("scanner", "axis2"), ("calibration",),
                                   ("calibration", "covariance")])
def test_unknown_keys_refused(where):
    d = read_json_file(DATA / "calibrated_system.json")
    if where == ("scanner", "axis2"):
        d = read_json_file(SAMPLES / "raster128x96_system.json")
    _at(d, where)["frobnicate"] = 1
    with pytest.raises(FormatError) as e:
        _load_system(d)
    fld = ".".join(where + ("frobnicate",))
    assert e.value.field == fld and "unknown field; expected one of" in str(e.value)


def test_unknown_keys_other_kinds(tmp_path):
    for _name, kind, load, valid in examples(tmp_path):
        if kind == "system":
            continue
        d = copy.deepcopy(valid)
        d["extra"] = 1
        with pytest.raises(FormatError, match="extra: unknown field"):
            load(d)
    scene = read_json_file(SAMPLES / "room_scene.json")
    scene["objects"][1]["radius"] = 0.2  # a box has no radius
    with pytest.raises(FormatError, match=r"objects\[1\]\.radius: unknown field"):
        scene_from_dict(scene, "scene.json")
    m = read_json_file(SAMPLES / "room48_map.json")
    m["zero_crossings"]["polarty"] = "negative"
    with pytest.raises(FormatError, match=r"zero_crossings\.polarty: unknown field; "
                                          r"did you mean polarity\?"):
        map_from_dict(m, "map.json", SAMPLES)
    dist = read_json_file(SAMPLES / "calib_distances.json")
    dist["targets"][0]["sdt"] = 0.001
    with pytest.raises(FormatError, match=r"targets\[0\]\.sdt: unknown field; did you mean std"):
        _distances_loader(tmp_path)(dist)


WRONG_TYPES = [
    ("system", ("scanner", "f_mech"), "1570", "scanner.f_mech"),
    ("system", ("tdc", "n_bins"), 4096.5, "tdc.n_bins"),
    ("system", ("receiver", "image_size"), "192x1", "receiver.image_size"),
    ("system", ("speed_of_light",), True, "speed_of_light"),
    ("system", ("scanner",), [1, 2], "scanner"),
    ("system", ("version",), "1", "version"),
    ("calibrated", ("calibration", "rms_pixel"), "small", "calibration.rms_pixel"),
    ("calibrated", ("calibration", "fixed"), [1], "calibration.fixed[0]"),
    ("tttr-map", ("tdc", "binning"), "64", "tdc.binning"),
    ("tttr-map", ("photons",), 1, "photons"),
    ("tttr-map", ("shots",), [], "shots"),
    ("target-distances", ("std",), "0.002", "std"),
    ("target-distances", ("targets", 0, "distance"), "1.5", "targets[0].distance"),
    ("scene", ("objects", 0, "reflectivity"), "high", "objects[0].reflectivity"),
    ("scene", ("name",), 3, "name"),
]


@pytest.mark.parametrize("kind, path, value, fld", WRONG_TYPES)
def test_wrong_types_refused_naming_the_field(tmp_path, kind, path, value, fld):
    ex = {("calibrated" if n == "calibrated system" else k): (load, v)
          for n, k, load, v in examples(tmp_path)
          if n in ("nominal system", "calibrated system") or k != "system"}
    load, valid = ex[kind]
    d = copy.deepcopy(valid)
    _at(d, path[:-1])[path[-1]] = value
    with pytest.raises(FormatError) as e:
        load(d)
    assert e.value.field == fld, str(e.value)
    assert "expected" in str(e.value)


def test_every_bundled_json_loads():
    from mems_stereo.io.tttr_map import load_map
    from mems_stereo.model.system import load_system

    files = sorted(SAMPLES.glob("*.json")) + sorted(DATA.glob("*.json"))
    kinds = set()
    for f in files:
        d = read_json_file(f)
        fmt = d["format"]
        kinds.add(fmt)
        if fmt == "mems-stereo/system":
            load_system(f)
        elif fmt == "mems-stereo/tttr-map":
            load_map(f)
        elif fmt == "mems-stereo/scene":
            scene_from_dict(d, str(f), f.parent)
        else:
            _distances_loader_path(f)
    assert kinds == {f"mems-stereo/{k}" for k in SCHEMAS}


def _distances_loader_path(f: Path):
    from calib.calibrate import read_target_distances

    # each distances file names its own recordings (calib_*, imperfect_calib_*)
    read_target_distances(f, [read_json_file(f)["targets"][0]["recording"]])


def test_written_files_load_back():
    """What the package writes (systems of every preset, maps) passes the schema."""
    from mems_stereo.io.tttr_map import load_map, map_to_dict
    from mems_stereo.model.presets import PRESETS, TWO_AXIS_PRESETS
    from mems_stereo.model.system import system_to_dict

    assert set(TWO_AXIS_PRESETS) < set(PRESETS)  # one registry, the two-axis ones in it
    for make in PRESETS.values():
        system_from_dict(system_to_dict(make()), "preset")
    m = load_map(SAMPLES / "room48_map.json")
    map_from_dict(map_to_dict(m, "room48_system.json"), "map.json", SAMPLES)


def test_docs_formats_lists_every_declared_member():
    """docs/formats.md carries the table generated from the declared specs, per kind."""
    text = (ROOT / "docs" / "formats.md").read_text()
    for kind in SCHEMAS:
        m = re.search(rf"<!-- schema: {re.escape(kind)} -->\n(.*?)<!-- /schema -->", text,
                      re.S)
        assert m, f"docs/formats.md has no generated table for {kind}"
        assert m.group(1) == schema_markdown(kind), (
            f"docs/formats.md: the {kind} table differs from the specs; regenerate with "
            "python scripts/doc_schemas.py")
        documented = set(re.findall(r"^\| `([^`]+)`", m.group(1), re.M))
        assert documented == {p for p, _ in schema_rows(kind)}


def test_cli_one_line_exit_2(tmp_path, capsys):
    """The CLI reports a schema refusal as one line naming file, field and the fix."""
    from mems_stereo.cli import main

    d = read_json_file(SAMPLES / "nominal_system.json")
    d["scanner"]["phase_ofset"] = 0.01
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    assert main(["info", "--system", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.endswith(f"{bad}: scanner.phase_ofset: unknown field; did you mean phase_offset?")


# ------------------------------------------- mutation over every declared key

#: the characters a typo inserts or substitutes (keys are lower-case snake case)
_ALPHABET = "abcdefghijklmnopqrstuvwxyz0123456789_"
#: sampled insertions and substitutions per position (deletions, transpositions: all)
_PER_POSITION = 2


def all_typos(key: str, rng) -> list[str]:
    """One-character typos of ``key``: every deletion and every transposition of
    neighbours; at each position a deterministic sample of insertions and of
    substitutions (the keyboard neighbour, a doubled letter, and ``_PER_POSITION``
    further characters drawn by ``rng``)."""
    out = [key[:i] + key[i + 1:] for i in range(len(key))]
    out += [key[:i] + key[i + 1] + key[i] + key[i + 2:] for i in range(len(key) - 1)]
    for i in range(len(key) + 1):
        ins = {_neighbour(key[i - 1]) if i else "_", key[i - 1] if i else key[0]}
        ins |= set(rng.sample(_ALPHABET, _PER_POSITION))
        out += [key[:i] + c + key[i:] for c in sorted(ins)]
    for i in range(len(key)):
        sub = {_neighbour(key[i])} | set(rng.sample(_ALPHABET, _PER_POSITION))
        out += [key[:i] + c + key[i + 1:] for c in sorted(sub) if c != key[i]]
    seen, uniq = {key}, []
    for t in out:
        if t and t not in seen:
            seen.add(t)
            uniq.append(t)
    return uniq


def schema_objects(fields: dict, path: str = ""):
    """``(dotted path, members, parent Field or None)`` of every object whose members a
    schema declares: nested objects, list items, name-keyed values and each variant
    of a scene object (``objects[type=box]``)."""
    yield path, fields, None
    for name, f in fields.items():
        yield from _field_objects(f, f"{path}.{name}" if path else name)


def _field_objects(f: Field, path: str):
    if f.fields is not None:
        yield from schema_objects(f.fields, path)
    if f.values is not None:
        yield from _field_objects(f.values, f"{path}.<name>")
    if f.items is not None:
        yield from _field_objects(f.items, f"{path}[]")
    if f.variants is not None:
        for kind, members in f.variants[1].items():
            for p, m, _ in schema_objects(members, f"{path}[type={kind}]"):
                yield p, m, (f if p == f"{path}[type={kind}]" else None)


def _filled(fields: dict, variant_kind: str | None = None) -> dict:
    """An object with every declared member (``const`` members at their value; the
    others a placeholder: key checks come before value checks)."""
    d = {k: (f.const if f.const is not None else 0) for k, f in fields.items()}
    if variant_kind is not None:
        d["type"] = variant_kind
    return d


def test_every_declared_key_typo_refused_with_did_you_mean(capsys):
    """Each one-character typo of every key of every schema (util/schemas.py) is
    refused by the schema check with "did you mean KEY?" (100 %)."""
    import random

    from mems_stereo.util.jsonfile import FieldChecker, check_schema, check_value

    rng = random.Random(32)
    ck = FieldChecker("x.json")
    total, keys, other_keys, failures = 0, 0, 0, []
    for kind, top in SCHEMAS.items():
        for path, fields, variant in schema_objects(top):
            vkind = path.rsplit("[type=", 1)[1][:-1] if variant is not None else None
            valid = _filled(fields, vkind)
            for key in fields:
                keys += 1
                for typo in all_typos(key, rng):
                    if typo in fields:  # another declared key: not a typo of this one
                        other_keys += 1
                        continue
                    d = _renamed(valid, key, typo)
                    total += 1
                    try:
                        if variant is not None:  # the scene object's variants by "type"
                            check_value(d, variant, ck, path)
                        else:
                            check_schema(d, fields, ck, path)
                    except FormatError as e:
                        if f"did you mean {key}?" in str(e):
                            continue
                        failures.append(f"{kind}: {path}.{typo} (for {key}): {e}")
                    else:
                        failures.append(f"{kind}: {path}.{typo} (for {key}): accepted")
    refused = total - len(failures)
    with capsys.disabled():
        print(f"\nschema mutation test: {refused} of {total} one-character typos of {keys} "
              f"declared keys (all {len(SCHEMAS)} kinds) refused with the right did-you-mean "
              f"({100.0 * refused / total:.1f} %); {other_keys} typos that are other "
              "declared keys not counted")
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:30])
    assert keys > 120 and total > 10 * keys


def test_all_typos_helper():
    import random

    t = all_typos("ab", random.Random(0))
    assert {"a", "b", "ba"} <= set(t) and "ab" not in t and len(t) == len(set(t))
    assert all(abs(len(x) - 2) <= 1 for x in t)
    assert all(edit_distance_one(x, "ab") for x in t)


def edit_distance_one(a: str, b: str) -> bool:
    """An independent check (not the package's edit distance): ``a`` is one deletion,
    insertion, substitution or neighbour transposition away from ``b``."""
    if abs(len(a) - len(b)) > 1 or a == b:
        return False
    if len(a) == len(b):
        diff = [i for i in range(len(a)) if a[i] != b[i]]
        return len(diff) == 1 or (len(diff) == 2 and diff[1] == diff[0] + 1
                                  and a[diff[0]] == b[diff[1]] and a[diff[1]] == b[diff[0]])
    s, t = (a, b) if len(a) < len(b) else (b, a)
    return any(t[:i] + t[i + 1:] == s for i in range(len(t)))


MUTATED_CLI = [
    # (command line, file written, kind of the file, dotted key, typo)
    (["info", "--system", "{f}"], "s.json", "nominal_system.json", ("tdc", "bin_width"),
     "bin_widht"),
    (["simulate", "{f}", "-o", "{d}/o.h5"], "scene.json", "room_scene.json",
     ("objects", 0, "reflectivity"), "reflectivty"),
    (["calibrate", "{s}/calib_1.5m.h5", "--target-distances-file", "{f}", "-o", "{d}/c.json"],
     "dist.json", "calib_distances.json", ("targets", 0, "distance"), "distnace"),
    (["import", "{s}/room48.ptu", "--map", "{f}", "-o", "{d}/o.h5"], "map.json",
     "room48_map.json", ("zero_crossings", "rising_edge"), "rising_egde"),
]


@pytest.mark.parametrize("argv, name, src, key, typo", MUTATED_CLI,
                         ids=[m[1] for m in MUTATED_CLI])
def test_key_typo_through_the_cli(argv, name, src, key, typo, tmp_path, capsys):
    from mems_stereo.cli import main

    d = read_json_file(SAMPLES / src)
    parent = _at(d, key[:-1])
    new = _renamed(parent, key[-1], typo)
    parent.clear()
    parent.update(new)
    f = tmp_path / name
    f.write_text(json.dumps(d))
    if name == "map.json":  # the map names its system relative to itself
        (tmp_path / "room48_system.json").write_text((SAMPLES / "room48_system.json").read_text())
    args = [a.replace("{f}", str(f)).replace("{d}", str(tmp_path)).replace("{s}", str(SAMPLES))
            for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    dotted = ".".join(f"[{k}]" if isinstance(k, int) else k for k in key[:-1] + (typo,))
    dotted = dotted.replace(".[", "[")
    parent_dotted = dotted[:-len(typo)]
    assert err.endswith((f"{f}: {dotted}: unknown field; did you mean {key[-1]}?",
                         f"{f}: {parent_dotted}{key[-1]}: required field is missing; found "
                         f"{typo} — did you mean {key[-1]}?")), err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [name] + (["room48_system.json"] if name == "map.json" else []))
