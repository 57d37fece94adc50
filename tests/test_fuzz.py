"""The fuzz suite: malformed inputs through every command.

Every case must end with exit 2, exactly one line on stderr that names the
file or the option, no traceback, and no file created or changed.  Cases are
generated with fixed seeds (mutations of samples/, hypothesis for option
values); :data:`COUNT` tallies them (printed by ``-s``).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import random
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from fuzz_cases import (
    RAW_JSON,
    SAMPLES,
    chain,
    mkdir,
    mkfifo,
    nominal,
    recording_cases,
    system_mutations,
    truncations,
    write_bytes,
    write_json,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mems_stereo.cli import main

RNG = random.Random(15)


def snapshot(root: Path) -> dict:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink() or not p.exists():
            out[str(p)] = ("link",)
        elif p.is_file():
            out[str(p)] = (p.stat().st_size, hashlib.sha1(p.read_bytes()).hexdigest())
        elif p.is_dir():
            out[str(p)] = ("dir",)
        else:
            out[str(p)] = ("special",)
    return out


def run_cli(argv):
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = main(argv)
        except SystemExit as e:
            rc = e.code
    return rc, err.getvalue(), out.getvalue()


def check_refused(d: Path, argv: list[str], expect: str) -> str:
    """Run ``argv`` (``{d}``: ``d``, ``{s}``: the samples) in this process: exit 2, one
    error line naming ``expect``, nothing written or changed; returns the stderr text."""
    before = snapshot(d)
    samples_before = {p.name: p.stat().st_mtime_ns for p in SAMPLES.iterdir()}
    argv = [a.replace("{d}", str(d)).replace("{s}", str(SAMPLES)) for a in argv]
    rc, err, _ = run_cli(argv)
    lines = err.strip("\n").split("\n")
    assert rc == 2, f"exit {rc}, stderr: {err!r}"
    # one error line; an indented advice line may follow (the CLI's convention)
    assert lines[0] and (len(lines) == 1 or (len(lines) == 2 and lines[1].startswith("  "))), \
        f"expected one line, found {err!r}"
    assert "Traceback" not in err and "internal error" not in err, err
    assert expect in lines[0], f"{expect!r} not named in {lines[0]!r}"
    assert snapshot(d) == before, "a file was created or changed"
    assert {p.name: p.stat().st_mtime_ns for p in SAMPLES.iterdir()} == samples_before
    return err


# ------------------------------------------------------------- case tables

def _rec_cases():
    out = []
    for name, build in recording_cases(RNG):
        out.append((f"process-{name}", build, ["process", "{d}/m.h5", "-o", "{d}/o.ply"], "m.h5"))
        if "corrupt-truth" in name:  # found only after a whole calibration: too slow here
            continue
        out.append((f"calibrate-{name}", build,
                    ["calibrate", "{s}/calib_1.5m.h5", "{d}/m.h5", "-o", "{d}/c.json"], "m.h5"))
    for name, build in truncations("room.h5", "m.h5", RNG, 12):
        out.append((f"process-{name}", build, ["process", "{d}/m.h5", "-o", "{d}/o.ply"], "m.h5"))
    for name, build in truncations("calib_2.5m.h5", "m.h5", RNG, 6):
        out.append((f"calibrate-{name}", build,
                    ["calibrate", "{s}/calib_1.5m.h5", "{d}/m.h5", "-o", "{d}/c.json"], "m.h5"))
    return out


SYSTEM_CMDS = [["info", "--system", "{d}/s.json"],
               ["simulate", "{s}/room_scene.json", "-o", "{d}/o.h5", "--system", "{d}/s.json"],
               ["process", "{s}/room.h5", "-o", "{d}/o.ply", "--system", "{d}/s.json"],
               ["calibrate", "{s}/calib_1.5m.h5", "-o", "{d}/c.json", "--system", "{d}/s.json"],
               ["plot", "acquisition", "-o", "{d}/a.png", "--system", "{d}/s.json"]]


def _system_cases():
    out = []
    muts = system_mutations()
    for i, (name, fn) in enumerate(muts):
        s = nominal()
        res = fn(s)
        s = s if res is None else res
        for k in (i % 5, (i + 2) % 5):
            out.append((f"system-{name}-{SYSTEM_CMDS[k][0]}", write_json("s.json", s),
                        SYSTEM_CMDS[k], "s.json"))
    for name, raw in RAW_JSON:
        for k in range(5):
            out.append((f"system-raw-{name}-{k}", write_bytes("s.json", raw), SYSTEM_CMDS[k],
                        "s.json"))
    return out


def _scene_cases():
    scene = json.loads((SAMPLES / "room_scene.json").read_text())
    argv = ["simulate", "{d}/sc/scene.json", "-o", "{d}/o.h5", "--shots", "10"]
    out = []

    def in_sc(build):
        return chain(mkdir("sc"), build)
    for name, raw in RAW_JSON:
        out.append((f"scene-raw-{name}", in_sc(write_bytes("sc/scene.json", raw)), argv,
                    "scene.json"))
    for f, v in [("absolute", "/etc/hostname"), ("dotdot", "../secret.ply"),
                 ("missing", "none.ply"), ("fifo", "pipe.ply"), ("dir", "sub"),
                 ("empty", ""), ("number", 3)]:
        s = dict(scene)
        s["objects"] = list(scene["objects"]) + [{"type": "mesh", "file": v}]
        extra = {"fifo": mkfifo("sc/pipe.ply"), "dir": mkdir("sc/sub"),
                 "dotdot": write_bytes("secret.ply", b"ply\n")}.get(f)
        b = chain(in_sc(write_json("sc/scene.json", s)), *( [extra] if extra else []))
        out.append((f"scene-mesh-{f}", b, argv, "scene.json"))
    for name, v in [("no-objects", {"objects": []}), ("objects-str", {"objects": "x"}),
                    ("radius-neg", {"objects": [{"type": "sphere", "center": [0, 0, 2],
                                                 "radius": -1}]}),
                    ("type-bogus", {"objects": [{"type": "torus"}]}),
                    ("center-nan", {"objects": [{"type": "sphere", "center": [0, 0, "x"],
                                                 "radius": 1}]})]:
        out.append((f"scene-{name}", in_sc(write_json("sc/scene.json", v)), argv, "scene.json"))
    return out


def _distance_cases():
    d0 = json.loads((SAMPLES / "calib_distances.json").read_text())
    argv = ["calibrate", "{s}/calib_1.5m.h5", "{s}/calib_2.5m.h5", "-o", "{d}/c.json",
            "--target-distances-file", "{d}/dist.json"]
    out = [(f"distances-raw-{n}", write_bytes("dist.json", r), argv, "dist.json")
           for n, r in RAW_JSON]
    text = json.dumps(d0)
    first = next(iter(d0.get("distances", d0)), None) if isinstance(d0, dict) else None
    if first is not None:
        dup = text.replace("{", "{" + json.dumps(first) + ": 1.0, ", 2)
        out.append(("distances-duplicate", write_bytes("dist.json", dup.encode()), argv,
                    "dist.json"))
    out.append(("distances-list", write_json("dist.json", [1, 2]), argv, "dist.json"))
    return out


def _ply(n=50, props=("x", "y", "z", "range"), fmt="binary_little_endian"):
    head = ["ply", f"format {fmt} 1.0", f"element vertex {n}"]
    head += [f"property double {p}" for p in props] + ["end_header"]
    body = np.random.default_rng(1).normal(size=(n, len(props))).astype("<f8").tobytes()
    return ("\n".join(head) + "\n").encode() + body


def _pcd(n=50, fields=("x", "y", "z")):
    head = ["VERSION 0.7", "FIELDS " + " ".join(fields), "SIZE " + " 8" * len(fields),
            "TYPE" + " F" * len(fields), "COUNT" + " 1" * len(fields), f"WIDTH {n}",
            "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", "DATA binary"]
    head[2] = "SIZE" + " 8" * len(fields)
    body = np.zeros((n, len(fields))).tobytes()
    return ("\n".join(head) + "\n").encode() + body


def _las(scale=1e-4, cut=None):
    import laspy

    h = laspy.LasHeader(point_format=6, version="1.4")
    h.scales = np.full(3, 1e-4)
    las = laspy.LasData(h)
    las.x = las.y = las.z = np.arange(20, dtype=float)
    buf = io.BytesIO()
    las.write(buf)
    data = bytearray(buf.getvalue())
    if scale != 1e-4:  # scale factors at byte 131 of the public header block
        data[131:155] = np.full(3, scale).tobytes()
    return bytes(data[:cut] if cut else data)


CLOUD_CMDS = [lambda f: ["export", f"{{d}}/{f}", "-o", "{d}/o.pcd"],
              lambda f: ["render", f"{{d}}/{f}", "-o", "{d}/o.png"],
              lambda f: ["plot", "cloud", f"{{d}}/{f}", "-o", "{d}/o.png"],
              lambda f: ["view", f"{{d}}/{f}"]]


def _cloud_cases():
    good = _ply()
    files = [("ply-no-z", "c.ply", _ply(props=("x", "y", "range"))),
             ("ply-garbage", "c.ply", b"\x00\x01garbage" * 10),
             ("ply-empty", "c.ply", b""),
             ("ply-count-neg", "c.ply", good.replace(b"vertex 50", b"vertex -5")),
             ("ply-count-abc", "c.ply", good.replace(b"vertex 50", b"vertex abc")),
             ("ply-huge-count", "c.ply", good.replace(b"vertex 50", b"vertex 999999999")),
             ("ply-ascii-short", "c.ply", _ply(fmt="ascii")[:120]),
             ("ply-no-end", "c.ply", b"ply\nformat ascii 1.0\n"),
             ("pcd-no-z", "c.pcd", _pcd(fields=("x", "y"))),
             ("pcd-truncated", "c.pcd", _pcd()[:-100]),
             ("pcd-garbage", "c.pcd", b"nothing here"),
             ("las-scale-0", "c.las", _las(scale=0.0)),
             ("las-scale-nan", "c.las", _las(scale=float("nan"))),
             ("las-truncated", "c.las", _las(cut=400)),
             ("las-header-only", "c.las", _las(cut=100)),
             ("las-garbage", "c.las", b"LASF" + b"\x00" * 50),
             ("wrong-ext", "c.txt", good)]
    for _i in range(8):
        cut = RNG.randrange(len(good) - 200, len(good) - 1)
        files.append((f"ply-truncated-{cut}", "c.ply", good[:cut]))
    out = []
    for name, fname, data in files:
        for k, cmd in enumerate(CLOUD_CMDS):
            out.append((f"cloud-{name}-{cmd(fname)[0]}{k}", write_bytes(fname, data),
                        cmd(fname), fname))
    return out


def _hist_file(d: Path, mutate=None, name="h.h5"):
    import h5py

    from mems_stereo.io.histograms import write_histograms

    a = np.ones((1, 8, 16), np.int32)
    write_histograms(d / name, a, a, a)
    if mutate:
        with h5py.File(d / name, "r+") as f:
            mutate(f)


def _hist_cases():
    import h5py

    def rep(n, v):
        def m(f):
            del f[n]
            f[n] = v
        return m
    muts = [("missing-raw", lambda f: f.__delitem__("raw")),
            ("negative", rep("signal", -np.ones((1, 8, 16), np.int32))),
            ("float", rep("noise", np.ones((1, 8, 16)))),
            ("shape-mismatch", rep("noise", np.ones((1, 8, 15), np.int32))),
            ("1d", rep("raw", np.ones(5, np.int32))),
            ("version-abc", lambda f: f.attrs.__setitem__("version", "abc")),
            ("version-nan", lambda f: f.attrs.__setitem__("version", np.nan)),
            ("format-missing", lambda f: f.attrs.__delitem__("format")),
            ("external-link", lambda f: f.__setitem__("x", h5py.ExternalLink("/etc/passwd", "/")))]
    argv = ["plot", "histograms", "{d}/h.h5", "-o", "{d}/o.png"]
    out = [(f"hist-{n}", (lambda d, m=m: _hist_file(d, m)), argv, "h.h5") for n, m in muts]
    out += [(f"hist-truncate-{c}", (lambda d, c=c: (_hist_file(d, None, "full.h5"),
                                                     (d / "h.h5").write_bytes(
                                                         (d / "full.h5").read_bytes()[:c]))),
             argv, "h.h5") for c in (0, 10, 500, 2000)]
    return out


# every command's inputs as FIFOs, directories and missing files (groups 8 and 4)
INPUT_SLOTS = [
    (["process", "{d}/X", "-o", "{d}/o.ply"], "X"),
    (["calibrate", "{d}/X", "-o", "{d}/c.json"], "X"),
    (["export", "{d}/X.ply", "-o", "{d}/o.las"], "X.ply"),
    (["render", "{d}/X.ply", "-o", "{d}/o.png"], "X.ply"),
    (["view", "{d}/X.ply"], "X.ply"),
    (["plot", "cloud", "{d}/X.ply", "-o", "{d}/o.png"], "X.ply"),
    (["plot", "histograms", "{d}/X", "-o", "{d}/o.png"], "X"),
    (["simulate", "{d}/X", "-o", "{d}/o.h5"], "X"),
    (["info", "--system", "{d}/X"], "X"),
    (["process", "{s}/room.h5", "--system", "{d}/X", "-o", "{d}/o.ply"], "X"),
    (["calibrate", "{s}/calib_1.5m.h5", "--target-distances-file", "{d}/X", "-o", "{d}/c.json"],
     "X"),
    (["plot", "acquisition", "--system", "{d}/X", "-o", "{d}/a.png"], "X"),
]


def _path_cases():
    out = []
    for argv, name in INPUT_SLOTS:
        tag = "-".join(a for a in argv[:2] if not a.startswith("{"))
        out.append((f"fifo-{tag}-{len(out)}", mkfifo(name), argv, name))
        out.append((f"dir-{tag}-{len(out)}", mkdir(name), argv, name))
        out.append((f"missing-{tag}-{len(out)}", lambda d: None, argv, name))
    outs = [(["process", "{s}/room.h5", "-o", "O"], ".ply"),
            (["process", "{s}/room.h5", "-o", "{d}/o.ply", "--labels", "O"], ".h5"),
            (["process", "{s}/room.h5", "-o", "{d}/o.ply", "--histograms", "O"], ".h5"),
            (["simulate", "{s}/room_scene.json", "-o", "O"], ".h5"),
            (["calibrate", "{s}/calib_1.5m.h5", "-o", "O"], ".json"),
            (["export", "{d}/c.ply", "-o", "O"], ".las"),
            (["render", "{d}/c.ply", "-o", "O"], ".png"),
            (["plot", "cloud", "{d}/c.ply", "-o", "O"], ".png"),
            (["plot", "acquisition", "-o", "O"], ".png"),
            (["info", "--plot", "O"], ".png")]
    cloud = write_bytes("c.ply", _ply())
    for argv, ext in outs:
        opt = argv[argv.index("O") - 1]
        bad = {"is-dir": (chain(cloud, mkdir(f"out{ext}")), f"{{d}}/out{ext}"),
               "under-file": (chain(cloud, write_bytes("f", b"x")), f"{{d}}/f/out{ext}"),
               "too-long": (cloud, "{d}/" + "n" * 300 + ext),
               "fifo": (chain(cloud, mkfifo(f"p{ext}")), f"{{d}}/p{ext}"),
               "bad-ext": (cloud, "{d}/out.xyz"),
               # a folder that exists and looks writable but takes no new file
               "virtual-fs": (cloud, f"/proc/out{ext}"),
               "virtual-fs-sub": (cloud, f"/proc/sub/out{ext}")}
        for k, (b, path) in bad.items():
            if k == "bad-ext" and ext in (".h5", ".json"):
                continue
            if k.startswith("virtual-fs") and not Path("/proc/self").is_dir():
                continue
            a = [path if x == "O" else x for x in argv]
            out.append((f"out-{k}-{argv[0]}{opt}", b, a, opt))
    # demo: its sample folder and its output folder
    for name, b, argv, expect in [
            ("missing-samples", lambda d: None, ["--samples", "{d}/none"], "--samples"),
            ("samples-file", write_bytes("f", b"x"), ["--samples", "{d}/f"], "--samples"),
            ("samples-empty", mkdir("e"), ["--samples", "{d}/e"], "--samples"),
            ("samples-fifo", mkfifo("p"), ["--samples", "{d}/p"], "--samples"),
            ("out-is-file", write_bytes("f", b"x"), ["-o", "{d}/f"], "--output"),
            ("out-under-file", write_bytes("f", b"x"), ["-o", "{d}/f/demo"], "--output"),
            ("out-is-samples", lambda d: None, ["-o", "{s}"], "--output"),
            ("out-too-long", lambda d: None, ["-o", "{d}/" + "n" * 300], "--output")]:
        out.append((f"demo-{name}", b, ["demo", "--no-render", *argv], expect))
    # the same recording twice (its data would count twice), also through a link;
    # recordings whose clouds would land on one file of the output folder
    link = lambda d: (d / "l.h5").symlink_to(SAMPLES / "room.h5")  # noqa: E731
    two = lambda d: [(d / x).mkdir() or shutil.copy(SAMPLES / "room.h5", d / x)  # noqa: E731
                     for x in ("a", "b")]
    out += [("rec-twice-process", lambda d: None,
             ["process", "{s}/room.h5", "{s}/room.h5", "-o", "{d}/x"], "room.h5"),
            ("rec-twice-link", link, ["process", "{s}/room.h5", "{d}/l.h5", "-o", "{d}/x"],
             "l.h5"),
            ("rec-twice-calibrate", lambda d: None,
             ["calibrate", "{s}/calib_1.5m.h5", "{s}/calib_1.5m.h5", "-o", "{d}/c.json"],
             "calib_1.5m.h5"),
            ("rec-same-stem", two, ["process", "{d}/a/room.h5", "{d}/b/room.h5", "-o", "{d}/x"],
             "room.ply")]
    # outputs clashing with each other
    out.append(("out-same-twice", lambda d: None,
                ["process", "{s}/room.h5", "-o", "{d}/x.ply", "--labels", "{d}/l.h5",
                 "--histograms", "{d}/l.h5"], "--histograms"))
    return out


# option values out of range, not finite, of the wrong kind (groups 4 and 9)
OPTION_CASES = [
    ("process", ["{s}/room.h5", "-o", "{d}/o.ply"],
     {"--confidence": ["0", "1", "-0.5", "nan", "inf", "2", "abc"],
      "--chunk-shots": ["0", "-5", "abc", "1.5"], "--false-alarm": ["0", "nan", "2", "-1"],
      "--min-range": ["-1", "nan", "0", "inf"], "--workers": ["0", "-2"],
      "--scheduler": ["tcp://", "tcp://host", "tcp://127.0.0.1:abc"],
      "--max-memory": ["abc", "-1", "1K", "nanG"]}),
    ("simulate", ["{s}/room_scene.json", "-o", "{d}/o.h5"],
     {"--shots": ["0", "-1", "abc"], "--background": ["-1", "nan", "inf"],
      "--dark": ["-1", "nan"], "--seed": ["-1", "1.5"], "--drift": ["nan", "5"],
      "--crosstalk": ["-0.1", "1", "nan"], "--system": ["nopreset"]}),
    ("calibrate", ["{s}/calib_1.5m.h5", "-o", "{d}/c.json"],
     {"--fix": ["bogus"], "--free": ["nope"], "--target-distance": ["inf", "-1", "0", "abc"],
      "--distance-std": ["0", "-1", "nan", "inf"], "--confidence": ["0", "1", "nan"]}),
    ("info", [], {"--shots": ["0", "-3"], "--distance": ["nan", "-1", "0", "inf"],
                  "--ratio": ["0", "nan", "-1"], "--system": ["nopreset"]}),
    ("render", ["{d}/c.ply", "-o", "{d}/o.png"],
     {"--width": ["0", "-1", "100000"], "--height": ["0", "abc"],
      "--point-size": ["-1", "0", "nan"], "--vmin": ["nan", "inf"], "--view": ["under"],
      "--cmap": ["jet"]}),
    ("view", ["{d}/c.ply"], {"--point-size": ["-1", "nan", "0"]}),
    ("plot histograms", ["{d}/h.h5", "-o", "{d}/o.png"],
     {"--max-code": ["0", "-1"], "--row": ["-1"]}),
    ("plot acquisition", ["-o", "{d}/a.png"],
     {"--shots": ["0"], "--distance": ["nan"], "--ratio": ["-1"]}),
]


def _option_cases():
    out = []
    for cmd, base, opts in OPTION_CASES:
        for o, values in opts.items():
            for v in values:
                argv = cmd.split() + base + [o, v]
                b = chain(write_bytes("c.ply", _ply()), lambda d: _hist_file(d))
                out.append((f"opt-{cmd}{o}={v}", b, argv, o))
    out.append(("opt-calibrate-fix-all", lambda d: None,
                ["calibrate", "{s}/calib_1.5m.h5", "-o", "{d}/c.json", "--fix", "theta0",
                 "theta_mech_max", "phase_offset", "tdc_offset", "baseline_x", "baseline_y",
                 "baseline_z"], "--fix"))
    out.append(("opt-render-vmin-vmax", lambda d: _hist_file(d),
                ["render", "{s}/room.h5", "-o", "{d}/o.png", "--vmin", "2", "--vmax", "1"],
                "--vmin"))
    out.append(("opt-calibrate-count", lambda d: None,
                ["calibrate", "{s}/calib_1.5m.h5", "-o", "{d}/c.json", "--target-distance",
                 "1", "2"], "--target-distance"))
    return out


CASES = [(f"{i:03d}-{c[0]}", *c[1:]) for i, c in enumerate(
    _rec_cases() + _system_cases() + _scene_cases() + _distance_cases() + _cloud_cases()
    + _hist_cases() + _path_cases() + _option_cases())]


def test_case_count_and_groups():
    """≥ 500 cases, and every group of the issue among them."""
    ids = [c[0] for c in CASES]
    assert len(ids) == len(set(ids))
    assert len(CASES) >= 500, len(CASES)
    groups = {"1 data loss": "out-", "2 garbage out": "cloud-ply-truncated",
              "3 inconsistent": "rec-zc-spacing", "4 tracebacks": "system-raw-utf16",
              "5 late/partial": "out-bad-ext", "6 interrupts": None,
              "7 claimed sizes": "rec-claims", "8 FIFO": "fifo-",
              "9 invalid values": "opt-", "10 path safety": "rec-external-link"}
    for g, prefix in groups.items():
        assert prefix is None or any(prefix in i for i in ids), g
    print(f"\nfuzz suite: {len(CASES)} generated malformed inputs")


def refusal_classes(case) -> tuple[str, tuple[str, str]]:
    """A case's two refusal classes: its group (the case name's first two words without
    the number, e.g. ``process-rec``, ``system-raw``, ``out-fifo``: command or file kind
    and what is malformed) and the pair (command, the file or option the error names)."""
    name, _, argv, expect = case
    return "-".join(name[4:].split("-")[:2]), (argv[0], expect)


def default_cases(cases: list, every: int = 5) -> set[str]:
    """The ids of the cases run by default, a deterministic subset: every case of a group
    of at most 4, the first case of each group and of each (command, named file or option)
    pair, and every ``every``-th case of a group in table order.  The others are marked
    ``stress`` (``pytest -m stress`` runs them; the two runs together are every case)."""
    size: dict = {}
    for c in cases:
        g = refusal_classes(c)[0]
        size[g] = size.get(g, 0) + 1
    keep, seen, pos = set(), set(), {}
    for c in cases:
        g, pair = refusal_classes(c)
        if size[g] <= 4 or pair not in seen or pos.get(g, 0) % every == 0:
            keep.add(c[0])
        seen.add(pair)
        pos[g] = pos.get(g, 0) + 1
    return keep


DEFAULT = default_cases(CASES)


def test_default_subset_hits_every_refusal_class():
    """The default run keeps every group and every (command, named input) pair, about a
    third of the cases; the rest are stress-marked, none dropped."""
    kept = [c for c in CASES if c[0] in DEFAULT]
    for i in (0, 1):
        assert {refusal_classes(c)[i] for c in kept} == {refusal_classes(c)[i] for c in CASES}
    assert 0.25 * len(CASES) < len(kept) < 0.45 * len(CASES), len(kept)
    assert DEFAULT <= {c[0] for c in CASES}


@pytest.mark.parametrize("case", [
    pytest.param(c, id=c[0], marks=() if c[0] in DEFAULT else pytest.mark.stress)
    for c in CASES])
def test_refused(case, tmp_path):
    _, build, argv, expect = case
    build(tmp_path)
    check_refused(tmp_path, argv, expect)


# --------------------------------------------------------- hypothesis: options

_NUMERIC = {"--confidence": (0, 1), "--false-alarm": (0, 1)}


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck),
          derandomize=True)
@given(opt=st.sampled_from(sorted(_NUMERIC)),
       value=st.one_of(st.floats(max_value=0.0), st.floats(min_value=1.0),
                       st.just(float("nan")), st.text(min_size=1, max_size=8).filter(
                           lambda s: not s.startswith("-"))))
def test_hypothesis_process_probabilities(opt, value, tmp_path_factory):
    d = tmp_path_factory.mktemp("h")
    text = value if isinstance(value, str) else repr(value)
    try:
        ok = 0 < float(text) < 1
    except ValueError:
        ok = False
    if ok:
        return
    check_refused(d, ["process", "{s}/room.h5", "-o", "{d}/o.ply", opt, text], opt)


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck),
          derandomize=True)
@given(data=st.binary(min_size=0, max_size=300))
def test_hypothesis_system_bytes(data, tmp_path_factory):
    """Random bytes as a system JSON: refused with the file named (or, if valid, accepted)."""
    d = tmp_path_factory.mktemp("hb")
    (d / "s.json").write_bytes(data)
    check_refused(d, ["info", "--system", "{d}/s.json"], "s.json")


# ------------------------------------------------- no input is ever modified

def _io_commands(d: Path):
    """(argv with OUT, {input option: path}) for every command with outputs."""
    (d / "c.ply").write_bytes(_ply())
    _hist_file(d)
    shutil.copy(SAMPLES / "room.h5", d / "r.h5")
    shutil.copy(SAMPLES / "nominal_system.json", d / "s.json")
    shutil.copy(SAMPLES / "room_scene.json", d / "scene.json")
    shutil.copy(SAMPLES / "calib_distances.json", d / "dist.json")
    return [
        ("process", ["process", "{d}/r.h5", "--system", "{d}/s.json", "-o", "{d}/o.ply",
                     "--labels", "{d}/l.h5", "--histograms", "{d}/h2.h5"],
         ["-o", "--labels", "--histograms"], ["r.h5", "s.json"]),
        ("simulate", ["simulate", "{d}/scene.json", "--system", "{d}/s.json", "-o", "{d}/o.h5"],
         ["-o"], ["scene.json", "s.json"]),
        ("calibrate", ["calibrate", "{d}/r.h5", "--system", "{d}/s.json",
                       "--target-distances-file", "{d}/dist.json", "-o", "{d}/o.json"],
         ["-o"], ["r.h5", "s.json", "dist.json"]),
        ("export", ["export", "{d}/c.ply", "-o", "{d}/o.las"], ["-o"], ["c.ply"]),
        ("render", ["render", "{d}/c.ply", "-o", "{d}/o.png"], ["-o"], ["c.ply"]),
        ("plot cloud", ["plot", "cloud", "{d}/c.ply", "-o", "{d}/o.png"], ["-o"], ["c.ply"]),
        ("plot histograms", ["plot", "histograms", "{d}/h.h5", "-o", "{d}/o.png"], ["-o"],
         ["h.h5"]),
        ("plot acquisition", ["plot", "acquisition", "--system", "{d}/s.json", "-o",
                              "{d}/o.png"], ["-o"], ["s.json"]),
        ("info", ["info", "--system", "{d}/s.json", "--plot", "{d}/o.png"], ["--plot"],
         ["s.json"]),
    ]


def _io_case_list():
    import tempfile

    with tempfile.TemporaryDirectory() as t:
        cmds = _io_commands(Path(t))
    return [(name, o, i) for name, _a, outs, ins in cmds for o in outs for i in ins]


@pytest.mark.parametrize("name,out_opt,inp", _io_case_list())
def test_output_onto_input_refused(name, out_opt, inp, tmp_path):
    """Every output option pointed at every input (also through a symbolic and a hard link)."""
    cmds = {c[0]: c for c in _io_commands(tmp_path)}
    _, argv, _, _ = cmds[name]
    for variant in ("same", "symlink", "hardlink", "dotted"):
        target = tmp_path / inp
        if variant == "symlink":
            target = tmp_path / f"link{Path(inp).suffix}"
            target.unlink(missing_ok=True)
            target.symlink_to(tmp_path / inp)
        elif variant == "hardlink":
            target = tmp_path / f"hard{Path(inp).suffix}"
            target.unlink(missing_ok=True)
            target.hardlink_to(tmp_path / inp)
        elif variant == "dotted":
            target = tmp_path / "." / inp
        a = list(argv)
        a[a.index(out_opt) + 1] = str(target)
        check_refused(tmp_path, a, out_opt if out_opt != "-o" else "--output")


# ------------------------------------------------------------------ scheduler

def test_unreachable_scheduler_fails_fast(tmp_path):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    t0 = time.monotonic()
    check_refused(tmp_path, ["process", "{s}/room.h5", "-o", "{d}/o.ply", "--scheduler",
                             f"tcp://127.0.0.1:{port}"], f"127.0.0.1:{port}")
    assert time.monotonic() - t0 < 5.0


@pytest.mark.parametrize("reply", [b"HTTP/1.1 400 Bad Request\r\n\r\n" * 4, b"", b"\x00" * 64],
                         ids=["http", "closed", "zeros"])
def test_scheduler_address_that_is_not_a_scheduler(reply, tmp_path):
    """Something answers at the address (a web server, a closed connection, zeros):
    one line naming the address, soon - not Dask's MemoryError from reading an
    HTTP reply as a frame length, nor its 30 s timeout."""
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    port = srv.getsockname()[1]

    def answer():
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            with contextlib.suppress(OSError):
                c.recv(4096)
                c.sendall(reply)
            c.close()

    threading.Thread(target=answer, daemon=True).start()
    t0 = time.monotonic()
    try:
        check_refused(tmp_path, ["process", "{s}/room.h5", "-o", "{d}/o.ply", "--scheduler",
                                 f"tcp://127.0.0.1:{port}"], f"127.0.0.1:{port}")
    finally:
        srv.close()
    assert time.monotonic() - t0 < 15.0


# ------------------------------------------------- bit flips: refused or processed

def _flip_case(tmp_path, seed):
    rng = random.Random(seed)
    data = bytearray((SAMPLES / "room.h5").read_bytes())
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(data))
        data[i] ^= 1 << rng.randrange(8)
    (tmp_path / "m.h5").write_bytes(bytes(data))
    rc, err, _ = run_cli(["process", str(tmp_path / "m.h5"), "-o", str(tmp_path / "o.ply")])
    assert "Traceback" not in err and "internal error" not in err, err
    if rc == 0:  # the flips hit data that stays valid: a complete cloud
        assert (tmp_path / "o.ply").is_file()
    else:
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "m.h5" in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["m.h5"]
    return rc


@pytest.mark.parametrize("seed", range(4))
def test_bit_flips_refused_or_processed(seed, tmp_path):
    _flip_case(tmp_path, seed)


@pytest.mark.stress
def test_bit_flips_many(tmp_path):
    codes = []
    for seed in range(4, 64):
        d = tmp_path / f"f{seed}"
        d.mkdir()
        codes.append(_flip_case(d, seed))
    print(f"\nbit flips: {codes.count(0)} processed, {codes.count(2)} refused")


def test_system_with_fewer_bins_names_the_recording(tmp_path):
    # a --system whose TDC has fewer bins than the recording's codes: the error names
    # the recording's file and dataset, the system used and the recording's own n_bins
    d = json.loads((SAMPLES / "nominal_system.json").read_text())
    d["tdc"]["n_bins"] = 64
    (tmp_path / "small.json").write_text(json.dumps(d))
    check_refused(tmp_path, ["process", "{s}/room.h5", "--system", "{d}/small.json",
                             "-o", "{d}/out.ply"],
                  "room.h5: /shots/bins: expected codes 0..64 (tdc.n_bins of the system used)")
