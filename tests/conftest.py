"""Shared fixtures: the paper's system and small helpers."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
os.environ.setdefault("MPLBACKEND", "Agg")

from mems_stereo.model.system import burkard2022


@pytest.fixture
def system():
    """The paper's Table 1 system (burkard2022 preset)."""
    return burkard2022()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# ------------------------------------------------------------ per-test CPU time
#
# ``MEMS_STEREO_TEST_CPU_LOG=FILE pytest ...`` appends one line per test as it ends:
# node id, CPU seconds of the test process and of the subprocesses it waited for (setup,
# call and teardown together), and wall seconds.  CPU time is what a 2-core CI machine
# pays, and it stays readable on a loaded machine where wall times do not.

_CPU_LOG = os.environ.get("MEMS_STEREO_TEST_CPU_LOG")


def assert_same_frames(got, ref) -> None:
    """Two lists of frames (:class:`mems_stereo.pipeline.frames.Frame`) are equal: indices,
    windows, counts, points and every attribute, bit for bit."""
    assert [f.index for f in got] == [f.index for f in ref]
    for a, b in zip(got, ref):
        assert (a.start, a.end, a.counts) == (b.start, b.end, b.counts)
        assert np.array_equal(a.cloud.points, b.cloud.points)
        assert a.cloud.attributes.keys() == b.cloud.attributes.keys()
        for k in b.cloud.attributes:
            assert np.array_equal(a.cloud.attributes[k], b.cloud.attributes[k]), k


def _cpu_now() -> float:
    import resource

    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


if _CPU_LOG:
    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import time

        c0, t0 = _cpu_now(), time.perf_counter()
        yield
        with open(_CPU_LOG, "a") as f:
            f.write(f"{item.nodeid}\t{_cpu_now() - c0:.3f}\t{time.perf_counter() - t0:.3f}\n")


# ------------------------------------------------------------ shared heavy results
#
# The bundled samples' calibrations and the imperfect-hardware comparison are
# deterministic and cost seconds each; several tests run them with the same arguments
# (``mems-stereo demo``, tests/test_cli_outputs.py, tests/test_demo_hardware.py, the
# ``calibrate --help`` example on a copy of the walls: files are keyed by content).  A
# test that asks for ``shared_results`` gets them computed once per test process
# (the tests that share are in one pytest-xdist group, pyproject's ``--dist loadgroup``)
# through the real functions; the callers' own code around them still runs.

_MEMO: dict = {}
_HELD: list = []  # objects memo keys name by identity (memoised_report), kept alive


def _memo_key(value):
    """A hashable, value-based stand-in for one argument of a memoised call."""
    from pathlib import Path

    from mems_stereo.model.system import System, system_to_dict

    if isinstance(value, (str, Path)) and Path(value).is_file():
        # by content: a copy of a sample (``mems-stereo samples -o ...``, as the --help
        # examples make) answers from the original's result
        import hashlib

        return ("file", hashlib.sha1(Path(value).read_bytes()).hexdigest())
    if isinstance(value, (str, Path)) and Path(value).is_dir():
        return ("dir", os.path.realpath(value))
    if isinstance(value, (list, tuple)):
        return tuple(_memo_key(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((k, _memo_key(v)) for k, v in value.items()))
    if isinstance(value, System):
        import json

        return ("system", json.dumps(system_to_dict(value), sort_keys=True,
                                     default=lambda o: o.tolist() if hasattr(o, "tolist")
                                     else repr(o)))
    if isinstance(value, np.ndarray):
        import hashlib

        return ("ndarray", value.dtype.str, value.shape,
                hashlib.sha1(np.ascontiguousarray(value).tobytes()).hexdigest())
    if value is None or isinstance(value, (bool, int, float, str, Path)):
        return value
    raise TypeError(f"no memo key for {type(value).__name__}")


def _calibrate_defaults(fn):
    """For :func:`mems_stereo.calib.calibrate.calibrate_system`: a function mapping its
    bound arguments to equal ones with its defaults spelt out as ``mems-stereo calibrate``
    passes them (``free=None`` is DEFAULT_FREE, ``harmonics`` (2, 3, 4, 5) and
    ``inflate_sigma=False`` are what it pops from ``fit_kwargs`` when absent), so that the
    documents' API calls and the CLI's share one fit.  None (no normalising) where
    calibrate_system's source no longer shows those defaults."""
    import inspect

    src = inspect.getsource(fn)
    if not all(s in src for s in ('fit_kwargs.pop("inflate_sigma", False)',
                                  'fit_kwargs.pop("harmonics", (2, 3, 4, 5))',
                                  "free=free")):
        return None
    from mems_stereo.calib.model import DEFAULT_FREE

    def normalise(args: dict) -> dict:
        a = dict(args)
        if a.get("free") is None:  # calib/fit.py fit_walls: None is DEFAULT_FREE
            a["free"] = list(DEFAULT_FREE)
        kw = dict(a.get("fit_kwargs") or {})
        if "harmonics" in kw and tuple(kw["harmonics"]) == (2, 3, 4, 5):
            del kw["harmonics"]
        if "inflate_sigma" in kw and kw["inflate_sigma"] is False:
            del kw["inflate_sigma"]
        a["fit_kwargs"] = kw
        return a
    return normalise


def memoised(name: str, fn, normalise=None):
    """``fn`` answering repeated calls with equal arguments (``progress`` aside) from
    the process-wide memo; the first call with those arguments runs ``fn``.
    ``normalise``: optional, maps the bound arguments (defaults applied) to those the
    key is made of (equal calls spelt differently)."""
    import inspect

    sig = inspect.signature(fn)

    def wrapper(*args, **kwargs):
        bound = sig.bind(*args, **kwargs)
        bound.apply_defaults()
        arguments = normalise(bound.arguments) if normalise else bound.arguments
        try:
            key = (name, tuple((k, _memo_key(v)) for k, v in arguments.items()
                               if k != "progress"))
        except TypeError:  # an argument without a value-based key: not memoised
            return fn(*args, **kwargs)
        if key not in _MEMO:
            _MEMO[key] = fn(*args, **kwargs)
        return _MEMO[key]
    return wrapper


def share_heavy_results(mp) -> None:
    """Patch (with MonkeyPatch ``mp``) the bundled samples' calibrations (one- and
    two-axis; also as :mod:`mems_stereo.calib` re-exports it) and the imperfect-hardware
    comparison to :func:`memoised` forms, and the calibration report's PDF drawing to
    :func:`memoised_report`'s."""
    import mems_stereo.calib as calib_pkg
    import mems_stereo.calib.calibrate as calib_mod
    import mems_stereo.calib.twoaxis as twoaxis_mod

    import mems_stereo.cli.demo_hardware as hw_mod

    for mod, name in ((calib_mod, "calibrate_system"), (calib_pkg, "calibrate_system"),
                      (twoaxis_mod, "calibrate_two_axis"),
                      (hw_mod, "hardware_comparison")):
        real = getattr(mod, name)
        real = getattr(real, "__wrapped_real__", real)
        norm = _calibrate_defaults(real) if name == "calibrate_system" else None
        m = memoised(f"{real.__module__}.{real.__qualname__}", real,  # one memo per function
                     norm)
        m.__wrapped_real__ = real
        mp.setattr(mod, name, m)
    import mems_stereo.viz.calib_report as report_mod

    real = report_mod.write_calibration_report
    mp.setattr(report_mod, "write_calibration_report",
               memoised_report(getattr(real, "__wrapped_real__", real)))


def memoised_report(real):
    """:func:`mems_stereo.viz.calib_report.write_calibration_report` drawing each PDF once
    per process: a repeated call for the same result object (the shared calibrations
    answer with one object), recordings of equal content, equal ``targets``, ``nominal``,
    ``max_std`` and header gets the first drawing's bytes written to its own path.  The
    header's ``date_utc`` is left out of the key: a repeated drawing carries the first
    one's date (seconds to minutes earlier in the same run).  Other suffixes, and
    arguments without a value-based key, run the real function."""
    import json
    from pathlib import Path

    from mems_stereo.util.atomic import atomic_output

    def wrapper(result, path, **kw):
        p = Path(path)
        if p.suffix.lower() != ".pdf":
            return real(result, path, **kw)
        header = {k: v for k, v in (kw.get("header") or {}).items() if k != "date_utc"}
        try:
            key = ("calibration report", id(result),
                   _memo_key([kw.get(k) for k in ("recordings", "targets", "nominal",
                                                  "max_std")]),
                   json.dumps(header, sort_keys=True, default=str))
        except TypeError:
            return real(result, path, **kw)
        if key not in _MEMO:
            real(result, path, **kw)
            _HELD.append(result)  # keyed by identity: kept alive, its id not reused
            _MEMO[key] = p.read_bytes()
        else:
            with atomic_output(p) as tmp:
                tmp.write_bytes(_MEMO[key])
        return p
    wrapper.__wrapped_real__ = real
    return wrapper


@pytest.fixture
def shared_results(monkeypatch):
    """The heavy calls of :func:`share_heavy_results` memoised for this test."""
    share_heavy_results(monkeypatch)


# ------------------------------------------------------------ pytest-xdist groups
#
# Tests that share work (a module fixture, or ``shared_results`` across modules) run in
# one worker process, so that the work is done once per run.  pytest-xdist's own
# ``xdist_group`` mark does not group with pytest 9.2 (pytest-xdist issue #1386: the node
# id it rewrites is no longer used), so ``--dist loadgroup`` (pyproject.toml) schedules by
# this table: a group's tests are one unit of work, the larger units first.

XDIST_GROUPS = {
    # the bundled walls' calibrations (line sensor, Lissajous scanner), the failed fit of
    # room.h5 + floodlight.h5 and the imperfect-hardware comparison (shared_results);
    # test_cli_outputs' module fixture ctx
    "bundled_calibrations": (
        "tests/test_cli_outputs.py", "tests/test_demo.py", "tests/test_demo_hardware.py",
        "tests/test_calib_walls.py",
        "tests/test_viz_calib_report.py::test_report_for_the_bundled_walls",
        "tests/test_twoaxis_calib.py::test_cli_calibrates_the_sample_walls",
        "tests/test_calib_cli.py::test_recordings_that_are_not_flat_walls_fail_cleanly",
        "tests/test_calib_cli.py::test_failed_calibration_writes_the_pdf_report",
        # the --help examples: lines that several commands' examples start with run once
        # (tests/test_docs.py), and calibrate's example is the demo's calibration (a copy
        # of the same walls: shared_results keys files by content)
        "tests/test_docs.py::test_every_help_example_runs",
        # the documents whose blocks calibrate the bundled walls (line sensor: the README's
        # and docs/calibration.md's commands, the Python calls of docs/calibration.md and
        # docs/interchange.md; the Lissajous walls: docs/two_axis.md)
        *(f"tests/test_docs.py::test_every_code_block_of_the_docs_runs[{d}.md]"
          for d in ("README", "calibration", "interchange", "two_axis"))),
    "calib_fit": ("tests/test_calib_fit.py",),          # the good walls and their free fit
    "dask_cluster": ("tests/test_distributed.py",),     # one LocalCluster
    "code_metrics": ("tests/test_code_metrics.py",),    # one pass of the checker
}


def xdist_group_of(nodeid: str) -> str | None:
    """The group of XDIST_GROUPS whose entry names this test (its file, or its function
    with any parameters), else None."""
    for group, entries in XDIST_GROUPS.items():
        for e in entries:
            if nodeid == e or nodeid.startswith((e + "::", e + "[")):
                return group
    return None


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook: unknown without pytest-xdist
def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class TableGroupScheduling(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group_of(nodeid) or super()._split_scope(nodeid)

    return TableGroupScheduling(config, log)
