"""Malformed inputs for the fuzz suite (tests/test_fuzz.py): generated, seeded.

Each case is ``(id, build, argv, expect)``: ``build(dir)`` writes the case's
files into ``dir`` (copies and mutations of samples/), ``argv`` is the command
line with ``{d}`` for that folder and ``{s}`` for samples/, and ``expect`` is
a word the one error line must contain (the file or the option).
"""

from __future__ import annotations

import json
import os
import random
import shutil
from pathlib import Path

import h5py
import numpy as np

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
REC = "room.h5"


# ------------------------------------------------------------------ builders

def copy(name, dst="in.h5"):
    def b(d: Path):
        shutil.copy(SAMPLES / name, d / dst)
    return b


def h5mut(fn, src=REC, dst="m.h5"):
    """Copy ``src`` to ``dst`` and apply ``fn(h5py.File)``."""
    def b(d: Path):
        shutil.copy(SAMPLES / src, d / dst)
        with h5py.File(d / dst, "r+") as f:
            fn(f, d)
    return b


def _replace(f, path, data, **kw):
    del f[path]
    f.create_dataset(path, data=data, **kw)


def rep(path, value):
    """A mutation ``m(f, d)`` replacing dataset ``path`` by ``value`` (or ``value(f)``,
    computed before the old dataset is deleted)."""
    def m(f, d):
        v = value(f) if callable(value) else value
        del f[path]
        f[path] = v
    return m


def external_link(f, d):
    """A mutation adding an external link to a host file."""
    (d / "secret.txt").write_text("secret")
    f["x"] = h5py.ExternalLink(str(d / "secret.txt"), "/")


def _system(f):
    return json.loads(f["system"][()])


def _set_system(f, d):
    del f["system"]
    f.create_dataset("system", data=d if isinstance(d, (str, bytes, np.ndarray))
                     else json.dumps(d))


def sysmut(fn):
    def m(f, d):
        s = _system(f)
        out = fn(s)
        _set_system(f, s if out is None else out)
    return m


def leaf_paths(d, pre=()):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from leaf_paths(v, pre + (k,))
        else:
            yield pre + (k,)


def _at(d, path):
    for k in path[:-1]:
        d = d[k]
    return d


def delete(path):
    def fn(s):
        del _at(s, path)[path[-1]]
    return fn


def setv(path, value):
    def fn(s):
        _at(s, path)[path[-1]] = value
    return fn


def nominal():
    return json.loads((SAMPLES / "nominal_system.json").read_text())


# system JSON mutations: (name, fn on the dict or raw text)
OPTIONAL = {("scanner", "phase_offset"), ("tdc", "offset"), ("calibration",)}


def system_mutations():
    out = []
    s0 = nominal()
    for p in leaf_paths(s0):
        if p not in OPTIONAL:
            out.append((f"del-{'.'.join(p)}", delete(p)))
        out.append((f"str-{'.'.join(p)}", setv(p, "x")))
    implausible = [(("scanner", "theta_mech_max"), 1e3), (("laser", "pulse_fwhm"), 1.0),
                   (("speed_of_light",), 1.0), (("speed_of_light",), 1e300),
                   (("scanner", "f_mech"), 0.0), (("tdc", "n_bins"), 0),
                   (("tdc", "n_bins"), 70000), (("receiver", "image_size"), [65536, 1]),
                   (("tdc", "bin_width"), 1.0), (("laser", "f_rep"), -5.0),
                   (("version",), 1.5), (("version",), True), (("version",), 2),
                   (("format",), "other"), (("scanner", "theta0"), 4.0),
                   (("receiver", "camera_matrix"), [[1, 0], [0, 1]]),
                   (("scanner", "normal_basis"), [[1, 0, 0], [1, 0, 0]]),
                   (("scanner", "laser_direction"), [0, 0, 0]),
                   (("receiver", "dist_coeffs"), [0, 0, 0]),
                   (("receiver", "pixel_pitch"), [0, 1e-5])]
    for p, v in implausible:
        out.append((f"bad-{'.'.join(p)}={v}"[:60], setv(p, v)))
    return out


RAW_JSON = [
    ("invalid-json", b"{\"format\": "),
    ("utf16", json.dumps(nominal()).encode("utf-16")),
    ("invalid-utf8", b"{\"format\": \"\xff\xfe\"}"),
    ("deep-nesting", b"[" * 1000 + b"]" * 1000),
    ("huge-int", b"{\"version\": " + b"9" * 5000 + b"}"),
    ("duplicate-key", b"{\"version\": 1, \"version\": 1}"),
    ("nan-literal", json.dumps(nominal()).replace("0.0", "NaN", 1).encode()),
    ("not-object", b"[1, 2, 3]"),
    ("empty", b""),
]


# ------------------------------------------------------------ recordings

def recording_cases(rng: random.Random):
    cases = []

    def add(name, fn, **kw):
        cases.append((f"rec-{name}", h5mut(fn, **kw)))

    for ds in ("system", "shots/time", "shots/bins", "scanner/zero_crossings",
               "scanner/rising"):
        add(f"missing-{ds}", lambda f, d, ds=ds: f.__delitem__(ds))
    for name, v in [("format-missing", None), ("format-wrong", "other"), ("format-int", 3)]:
        def fn(f, d, v=v):
            if v is None:
                del f.attrs["format"]
            else:
                f.attrs["format"] = v
        add(name, fn)
    for name, v in [("abc", "abc"), ("nan", np.nan), ("array", np.array([1, 1])),
                    ("1.5", 1.5), ("true", True), ("2", 2), ("-1", -1), ("missing", None)]:
        def fn(f, d, v=v):
            if v is None:
                del f.attrs["version"]
            else:
                f.attrs["version"] = v
        add(f"version-{name}", fn)
    for name, m in system_mutations():
        add(f"system-{name}", sysmut(m))
    for name, raw in RAW_JSON:
        add(f"system-raw-{name}", lambda f, d, raw=raw: _set_system(
            f, np.array(raw or b" ", dtype=f"S{max(len(raw), 1)}")))
    add("system-array", lambda f, d: _replace(f, "system", np.zeros(3)))
    add("system-group", lambda f, d: (f.__delitem__("system"), f.create_group("system")))
    K = 800
    t = np.arange(K) / 20000.0
    add("time-float16", lambda f, d: _replace(f, "shots/time", t.astype(np.float16)))
    add("time-float32", lambda f, d: _replace(f, "shots/time", t.astype(np.float32)))
    add("time-int", lambda f, d: _replace(f, "shots/time", np.arange(K)))
    for _i in range(4):
        k = rng.randrange(1, K)
        add(f"time-nan-{k}", lambda f, d, k=k: _replace(f, "shots/time",
                                                         np.where(np.arange(K) == k, np.nan, t)))
        add(f"time-back-{k}", lambda f, d, k=k: _replace(f, "shots/time",
                                                          np.where(np.arange(K) == k, 0.0, t)))
    add("time-inf", lambda f, d: _replace(f, "shots/time", np.append(t[:-1], np.inf)))
    add("time-2d", lambda f, d: _replace(f, "shots/time", t.reshape(2, -1)))
    add("time-short", lambda f, d: _replace(f, "shots/time", t[:-1]))
    b = None

    def bins(f):
        return f["shots/bins"][()]
    add("bins-uint8", lambda f, d: _replace(f, "shots/bins", bins(f).astype(np.uint8)))
    add("bins-int16", lambda f, d: _replace(f, "shots/bins", bins(f).astype(np.int16)))
    add("bins-float", lambda f, d: _replace(f, "shots/bins", bins(f).astype(np.float64)))
    add("bins-2d", lambda f, d: _replace(f, "shots/bins", bins(f)[:, 0, :]))
    add("bins-width", lambda f, d: _replace(f, "shots/bins", bins(f)[:, :, :-1]))
    for _i in range(4):
        k, c = rng.randrange(K), rng.randrange(4097, 65536)

        def fn(f, d, k=k, c=c):
            a = bins(f)
            a[k, 0, rng.randrange(a.shape[2])] = c
            _replace(f, "shots/bins", a, chunks=(100, 1, 192), compression="gzip")
        add(f"bins-code-{c}-shot-{k}", fn)
    zc = None

    def zcs(f):
        return f["scanner/zero_crossings"][()], f["scanner/rising"][()]
    add("zc-nan", lambda f, d: _replace(f, "scanner/zero_crossings",
                                        np.where(np.arange(zcs(f)[0].size) == 3, np.nan,
                                                 zcs(f)[0])))
    add("zc-decreasing", lambda f, d: _replace(f, "scanner/zero_crossings", zcs(f)[0][::-1]))
    add("zc-one", lambda f, d: (_replace(f, "scanner/zero_crossings", zcs(f)[0][:1]),
                                _replace(f, "scanner/rising", zcs(f)[1][:1])))
    add("zc-float16", lambda f, d: _replace(f, "scanner/zero_crossings",
                                            zcs(f)[0].astype(np.float16)))
    add("rising-2", lambda f, d: _replace(f, "scanner/rising", zcs(f)[1] * 2))
    add("rising-short", lambda f, d: _replace(f, "scanner/rising", zcs(f)[1][:-1]))
    add("rising-all", lambda f, d: _replace(f, "scanner/rising", np.ones_like(zcs(f)[1])))
    add("rising-none", lambda f, d: _replace(f, "scanner/rising", np.zeros_like(zcs(f)[1])))
    # inverted polarity: still alternating and spaced for f_mech; the detections tell
    add("rising-inverted", lambda f, d: _replace(f, "scanner/rising", 1 - zcs(f)[1]))
    add("zc-spacing-x2", lambda f, d: _replace(f, "scanner/zero_crossings", zcs(f)[0] * 2))
    add("zc-spacing-half", lambda f, d: _replace(f, "scanner/zero_crossings", zcs(f)[0] / 2))
    add("truth-label-shape", lambda f, d: _replace(f, "truth/label",
                                                   np.zeros((3, 3), np.uint8)))
    add("truth-dataset", lambda f, d: (f.__delitem__("truth"),
                                       f.create_dataset("truth", data=1)))
    # path safety (group 10)

    def ext_link(f, d):
        (d / "secret.txt").write_text("secret")
        f["x"] = h5py.ExternalLink(str(d / "secret.txt"), "/")
    add("external-link", ext_link)

    def ext_time(f, d):
        (d / "host.bin").write_bytes(np.arange(800, dtype=np.float64).tobytes())
        del f["shots/time"]
        f.create_dataset("shots/time", shape=(800,), dtype=np.float64,
                         external=[(str(d / "host.bin"), 0, h5py.h5f.UNLIMITED)])
    add("external-storage", ext_time)
    add("soft-dangling", lambda f, d: f.__setitem__("y", h5py.SoftLink("/nowhere")))

    def virtual(f, d):
        t = f["shots/time"][()]
        with h5py.File(d / "src.h5", "w") as g:
            g["t"] = t
        lay = h5py.VirtualLayout(shape=t.shape, dtype=t.dtype)
        lay[:] = h5py.VirtualSource(str(d / "src.h5"), "t", shape=t.shape)
        del f["shots/time"]
        f.create_virtual_dataset("shots/time", lay)
    add("virtual-dataset", virtual)
    # resources (group 7)
    add("chunks-1x1x1", lambda f, d: _replace(f, "shots/bins", bins(f), chunks=(1, 1, 1)))

    def claims(f, d):
        s = _system(f)
        s["receiver"]["image_size"] = [4096, 4096]
        s["receiver"]["camera_matrix"][0][2] = 2047.5
        _set_system(f, s)
        del f["shots/bins"]
        f.create_dataset("shots/bins", shape=(800, 4096, 4096), dtype=np.uint16,
                         chunks=(1, 64, 4096), compression="gzip")
    add("claims-16M-pixels", claims)

    def claims_k(f, d):
        del f["shots/time"]
        f.create_dataset("shots/time", shape=(2_000_000_000,), dtype=np.float64,
                         chunks=(1 << 16,), compression="gzip")
    add("claims-2e9-shots", claims_k)
    # corrupt deflate chunks (HDF5 read errors after opening)
    for ds, fill in (("shots/bins", 0x00), ("shots/bins", 0xFF), ("truth/label", 0x00),
                     ("truth/label", 0xFF)):
        def corrupt(d, ds=ds, fill=fill):
            shutil.copy(SAMPLES / REC, d / "m.h5")
            with h5py.File(d / "m.h5", "r") as f:
                info = f[ds].id.get_chunk_info(0)
            with open(d / "m.h5", "r+b") as fh:
                fh.seek(info.byte_offset)
                fh.write(bytes([fill]) * min(info.size, 64))
        cases.append((f"rec-corrupt-{ds.replace('/', '-')}-{fill:02x}", corrupt))
    del b, zc
    return cases


def truncations(src: str, dst: str, rng: random.Random, n: int):
    size = (SAMPLES / src).stat().st_size if (SAMPLES / src).exists() else None
    out = []
    for _ in range(n):
        cut = rng.randrange(0, size)

        def b(d, cut=cut):
            data = (SAMPLES / src).read_bytes()[:cut]
            (d / dst).write_bytes(data)
        out.append((f"truncate-{src}-{cut}", b))
    return out


def write_bytes(name, data):
    def b(d):
        (d / name).write_bytes(data)
    return b


def write_json(name, obj):
    def b(d):
        (d / name).write_text(json.dumps(obj))
    return b


def mkfifo(name):
    def b(d):
        os.mkfifo(d / name)
    return b


def mkdir(name):
    def b(d):
        (d / name).mkdir()
    return b


def chain(*bs):
    def b(d):
        for x in bs:
            x(d)
    return b
