"""The source stays within its structural limits (scripts/code_metrics.py): module,
function and class size, returned tuples, parameter counts, private names used
across modules, import cycles and imports that go up the layers."""

from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _metrics():
    spec = importlib.util.spec_from_file_location("code_metrics",
                                                  ROOT / "scripts" / "code_metrics.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["code_metrics"] = mod
    spec.loader.exec_module(mod)
    return mod


METRICS = _metrics()
#: the kinds of breach scripts/code_metrics.py reports (test_every_kind_is_checked)
KINDS = ("class size", "deprecated module", "function size", "import cycle", "layer",
         "module size", "parameters", "private name", "returned tuple")


@functools.cache
def _breaches() -> dict[str, list[str]]:
    """The checker's findings, computed on first use (a few CPU seconds: not at
    collection, and once per test process; tests/conftest.py's XDIST_GROUPS keeps this
    module in one)."""
    return METRICS.breaches()


def test_every_kind_is_checked():
    assert sorted(_breaches()) == sorted(KINDS)


@pytest.mark.parametrize("kind", KINDS)
def test_no_breach(kind):
    found = _breaches()[kind]
    assert not found, f"{kind}:\n" + "\n".join(found)


def test_the_checker_sees_a_cycle_and_a_long_tuple(tmp_path):
    """The checks can fail: a two-module cycle and a 4-tuple return are found."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"a"}}
    assert METRICS._cycles(graph) == [["a", "b"]]
    import ast

    tree = ast.parse("def f():\n    return 1, 2, 3, 4\n")
    ret = next(n for n in ast.walk(tree) if isinstance(n, ast.Return))
    assert len(ret.value.elts) > METRICS.MAX_RETURNED_TUPLE


def test_imports_of_a_stage_are_found():
    """The import graph holds a stage's imports of earlier stages."""
    path = ROOT / "mems_stereo" / "pipeline" / "run.py"
    deps = METRICS.imports_of("mems_stereo.pipeline.run", path)
    assert "mems_stereo.pipeline.pass1" in deps
