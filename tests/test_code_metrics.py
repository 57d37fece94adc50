"""The source stays within its structural limits (scripts/code_metrics.py): module,
function and class size, returned tuples, parameter counts, private names used
across modules, import cycles and imports that go up the layers."""

from __future__ import annotations

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
BREACHES = METRICS.breaches()


@pytest.mark.parametrize("kind", sorted(BREACHES))
def test_no_breach(kind):
    assert not BREACHES[kind], f"{kind}:\n" + "\n".join(BREACHES[kind])


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
