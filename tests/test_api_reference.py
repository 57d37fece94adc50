"""The API reference (docs/api, Sphinx autodoc + napoleon) builds with no warning.

The build runs in a subprocess, as a user runs it
(``python -m sphinx -W --keep-going -b html docs/api <out>``), into a fresh
folder; any warning (bad docstring markup, a public name that cannot be
imported, an ambiguous cross-reference) fails the test and is printed.
The build (~21 CPU s) is marked ``stress`` (``pytest -m stress``); the index check runs
by default.
"""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

import mems_stereo as ms

pytest.importorskip("sphinx", reason="the dev extra (pip install -e '.[dev]') installs sphinx")

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "docs" / "api"

#: the pages the index must list: one per public area
PAGES = ("toplevel", "model", "geometry", "physics", "io", "pipeline", "sim", "calib", "viz")


def _build(out: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONWARNINGS": "ignore"}
    return subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
         "-d", str(out / "doctrees"), str(SOURCE), str(out / "html")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
@pytest.mark.stress  # 21 CPU s (the Sphinx build): with the stress runs (pytest -m stress)
def test_api_reference_builds_without_warnings(tmp_path):
    proc = _build(tmp_path)
    assert proc.returncode == 0 and "WARNING" not in proc.stderr \
        and "ERROR" not in proc.stderr, f"sphinx warnings:\n{proc.stderr}"
    html = tmp_path / "html"
    for page in PAGES:
        assert (html / f"{page}.html").is_file(), page
    top = (html / "toplevel.html").read_text(encoding="utf-8")
    # every function of mems_stereo.__all__ is on the top-level page, with its example
    for name in ms.__all__:
        if inspect.isfunction(getattr(ms, name)):
            assert f">{name}<" in top, name
    assert top.count("&gt;&gt;&gt;") >= 29          # the examples are rendered
    pipeline = (html / "pipeline.html").read_text(encoding="utf-8")
    for name in ("process_recording", "process_split", "process_many", "PointCloud", "Settings"):
        assert name in pipeline, name


def test_api_reference_pages_are_listed():
    index = (SOURCE / "index.rst").read_text(encoding="utf-8")
    for page in PAGES:
        assert (SOURCE / f"{page}.rst").is_file(), page
        assert f"   {page}\n" in index, page
