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


def memoised(name: str, fn):
    """``fn`` answering repeated calls with equal arguments (``progress`` aside) from
    the process-wide memo; the first call with those arguments runs ``fn``."""
    import inspect

    sig = inspect.signature(fn)

    def wrapper(*args, **kwargs):
        bound = sig.bind(*args, **kwargs)
        bound.apply_defaults()
        try:
            key = (name, tuple((k, _memo_key(v)) for k, v in bound.arguments.items()
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
    comparison to :func:`memoised` forms."""
    import mems_stereo.calib as calib_pkg
    import mems_stereo.calib.calibrate as calib_mod
    import mems_stereo.calib.twoaxis as twoaxis_mod

    import mems_stereo.cli.demo_hardware as hw_mod

    for mod, name in ((calib_mod, "calibrate_system"), (calib_pkg, "calibrate_system"),
                      (twoaxis_mod, "calibrate_two_axis"),
                      (hw_mod, "hardware_comparison")):
        real = getattr(mod, name)
        real = getattr(real, "__wrapped_real__", real)
        m = memoised(f"{real.__module__}.{real.__qualname__}", real)  # one memo per function
        m.__wrapped_real__ = real
        mp.setattr(mod, name, m)


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
