"""Every public function and class of ``mems_stereo.__all__`` has a runnable example.

The examples are the ``>>>`` lines of the numpy-style ``Examples`` section of
each docstring; they run here with :mod:`doctest` (globals ``np`` and ``ms``),
so that a change of behaviour that an example shows fails the test suite.
"""

from __future__ import annotations

import doctest
import inspect

import numpy as np
import pytest

import mems_stereo as ms

#: the public functions and classes (modules and data such as ``PRESETS`` have no docstring)
PUBLIC = sorted(n for n in ms.__all__
                if inspect.isfunction(getattr(ms, n)) or inspect.isclass(getattr(ms, n)))

FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _examples(name: str) -> list[doctest.DocTest]:
    """The doctests of the object itself (not of its methods or of other names)."""
    obj = getattr(ms, name)
    finder = doctest.DocTestFinder(recurse=False)
    return [t for t in finder.find(obj, f"mems_stereo.{name}", globs={"np": np, "ms": ms})
            if t.examples]


def test_public_functions_are_listed():
    functions = [n for n in PUBLIC if inspect.isfunction(getattr(ms, n))]
    assert {"process_recording", "classify_recording", "read_recording"} <= set(functions)
    assert len(functions) >= 29


@pytest.mark.parametrize("name", PUBLIC)
def test_docstring_has_examples_section(name):
    doc = inspect.getdoc(getattr(ms, name)) or ""
    assert "\nExamples\n--------\n" in doc, f"{name}: no numpy-style Examples section"
    assert _examples(name), f"{name}: the Examples section has no >>> example"


@pytest.mark.parametrize("name", PUBLIC)
def test_docstring_examples_run(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # examples that write files write them here
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    for test in _examples(name):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"
    assert result.attempted > 0


def test_failing_example_is_caught():
    """The runner reports a wrong expected output (the test above can fail)."""
    def f():
        """Doc.

        Examples
        --------
        >>> 1 + 1
        3
        """
    test = doctest.DocTestFinder(recurse=False).find(f, "f", globs={})[0]
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    runner.run(test, out=lambda s: None)
    assert runner.summarize(verbose=False).failed == 1

