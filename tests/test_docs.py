"""Documentation that cannot drift: every code block of README.md and docs/*.md and every
``--help`` example runs, from a temporary folder outside the repository, against the
installed package.

A small Markdown collector finds the fenced blocks (```lang ... ```).  How each runs:

* ``python``: as a script by this interpreter (the installed package's), cwd a fresh
  temporary folder; the blocks of one document run in order in the same folder.
* ``bash``, ``sh``, ``console`` and blocks without a language: ``bash -e`` with the
  interpreter's ``bin/`` first on PATH (so ``mems-stereo`` is the installed one).
* ``json``: parsed (``json.loads``); nothing else.
* Indented (4-space) blocks are read as literal text — output listings, package
  lists — and not run; every command a reader is meant to type is in a fenced block.
* A block right after a line ``<!-- docs-test: skip REASON -->`` does not run; the test
  prints each with its reason.  The only such blocks are the README's two set-up
  commands (they install Debian packages as root and build ``.venv`` in the repository),
  its command that builds the API reference into the repository (the test suite builds
  it on its own), and the C++ reader of docs/interchange.md.

The ``--help`` examples (each command module's ``EXAMPLE`` lines and ``plot``'s per-figure
examples) run in order in a fresh folder per command, in this process through the CLI's
``main`` (each line as a process of its own paid the package's import again; the
``mems-stereo`` executable runs in the README's blocks and tests/test_wheel.py); lines that several commands'
examples begin with run once, and the other commands continue from a copy of the folder
they left (the same state); ``view`` opens a window, so its last line is only parsed;
``demo``'s example is the run of ``tests/test_demo.py``.

``tests/test_wheel.py`` (slow) builds a wheel and processes a bundled sample with
that non-editable install.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = re.compile(r"<!--\s*docs-test:\s*skip\b\s*(.*?)\s*-->")
FENCE = re.compile(r"^(```+|~~~+)\s*([\w+-]*)\s*$")


@dataclass
class Block:
    file: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    skip: str | None  # reason, or None when it runs


def collect(path: Path) -> list[Block]:
    """The fenced code blocks of one Markdown file, in order."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang, start = m.group(1), m.group(2).lower(), i
        j = i + 1
        while j < len(lines) and not lines[j].startswith(fence):
            j += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        sk = SKIP.search(prev)
        blocks.append(Block(path, start + 1, lang, "\n".join(lines[start + 1:j]) + "\n",
                            (sk.group(1) or "no reason given") if sk else None))
        i = j + 1
    return blocks


def _env(python: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["PATH"] = str(Path(python).parent) + os.pathsep + env.get("PATH", "")
    env.setdefault("MPLBACKEND", "Agg")
    return env


def run_block(block: Block, cwd: Path, python: str = sys.executable) -> None:
    """Execute one block in ``cwd``; fail with the block's place and output."""
    where = f"{block.file.relative_to(ROOT)}:{block.line} ({block.lang or 'no language'})"
    if block.lang == "json":
        try:
            json.loads(block.code)
        except json.JSONDecodeError as e:
            pytest.fail(f"{where}: not valid JSON: {e}")
        return
    if block.lang == "text":  # printed output shown in the docs: nothing to run
        return
    if block.lang == "python":
        cmd = [python, "-c", block.code]
    elif block.lang in ("", "bash", "sh", "console", "shell"):
        cmd = ["bash", "-e", "-c", block.code]
    else:
        pytest.fail(f"{where}: no rule to run a {block.lang!r} block (add one or a skip marker)")
    p = subprocess.run(cmd, cwd=cwd, env=_env(python), capture_output=True, text=True,
                       timeout=600)
    if p.returncode:
        pytest.fail(f"{where} failed (exit {p.returncode}):\n{block.code}\n--- stdout\n"
                    f"{p.stdout[-3000:]}\n--- stderr\n{p.stderr[-3000:]}")


def _outside_repository(tmp_path: Path) -> Path:
    assert ROOT not in tmp_path.resolve().parents, "the temporary folder is in the repository"
    return tmp_path


@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCS, ids=lambda d: d.name)
def test_every_code_block_of_the_docs_runs(doc, tmp_path):
    """One test per document, so that pytest-xdist spreads the documents over the cores."""
    cwd = _outside_repository(tmp_path / doc.stem)
    cwd.mkdir()
    for b in collect(doc):
        if b.skip is None:
            run_block(b, cwd)


def test_code_blocks_marked_not_to_run(capsys):
    n_run, skipped = 0, []
    for doc in DOCS:
        for b in collect(doc):
            if b.skip is not None:
                skipped.append(f"{b.file.relative_to(ROOT)}:{b.line} ({b.skip})")
            else:
                n_run += 1
    with capsys.disabled():
        print(f"\n[docs] {n_run} code blocks of README.md and docs/*.md run; "
              f"{len(skipped)} marked not to run: " + "; ".join(skipped))
    assert n_run >= 8
    # the README's set-up commands and API-reference build, the C++ reader of
    # docs/interchange.md, nothing else
    assert len(skipped) == 4, skipped


def help_examples() -> dict[str, list[str]]:
    """Example command lines per command (and per ``plot`` figure), as ``--help`` shows them."""
    from mems_stereo.cli import _load_commands, examples
    from mems_stereo.cli.plot import FIGURES

    out = {mod.NAME: examples(mod) for mod in _load_commands()}
    for fig, (_desc, lines) in FIGURES.items():
        out[f"plot {fig}"] = lines
    return out


def test_help_shows_the_examples():
    """Each command's (and each figure's) --help epilog holds its example lines verbatim."""
    from mems_stereo.cli import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if a.choices and "process" in a.choices).choices
    for name, lines in help_examples().items():
        parts = name.split()
        p = subs[parts[0]]
        if len(parts) > 1:
            p = next(a for a in p._actions if a.choices and parts[1] in a.choices).choices[parts[1]]
        text = p.format_help()
        for line in lines:
            assert line in text, (name, line)
        assert p.description, name


def _help_example_names() -> list[str]:
    # tests/test_demo.py runs the demo's example exactly
    return [name for name in help_examples() if name != "demo"]


#: the folder after the first lines of a command's examples, where another command's
#: examples begin with the same lines (in a fresh folder, so the same state): lines → copy
_HELP_STATES: dict[tuple, Path] = {}


def _shared_prefixes() -> set[tuple]:
    """Leading runs of example lines that more than one command's examples start with."""
    seen: dict[tuple, int] = {}
    for name in _help_example_names():
        lines = help_examples()[name]
        for k in range(1, len(lines) + 1):
            seen[tuple(lines[:k])] = seen.get(tuple(lines[:k]), 0) + 1
    return {k for k, n in seen.items() if n > 1}


def run_example_line(line: str, cwd: Path) -> None:
    """One ``mems-stereo ...`` example line, run in this process by the CLI's ``main`` from
    ``cwd`` (the entry point itself, a separate process, is run by the README's blocks in
    :func:`test_every_code_block_of_the_docs_runs` and by tests/test_wheel.py); fails with
    the line and its output unless it exits 0.  ``view`` opens a window: parsed only."""
    import contextlib
    import io

    from mems_stereo.cli import build_parser, main

    argv = shlex.split(line, comments=True)
    assert argv[0] == "mems-stereo", line
    if argv[1] == "view":  # opens a window: parse it, do not run it
        build_parser().parse_args(argv[1:])
        return
    out, err, here = io.StringIO(), io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv[1:])
    except SystemExit as e:  # usage errors (argparse)
        rc = e.code
    finally:
        os.chdir(here)
    assert rc == 0, f"{line}: exit {rc}\n{out.getvalue()[-2000:]}\n{err.getvalue()[-2000:]}"


# one pytest-xdist worker runs the examples (tests/conftest.py: XDIST_GROUPS), so that
# lines that several commands' examples start with (``mems-stereo samples``, ``process
# samples/room.h5 -o room.ply``) run once and the others start from a copy of the folder
# they left; ``calibrate``'s fit of the bundled walls is the demo's (``shared_results``)
@pytest.mark.slow
@pytest.mark.parametrize("name", _help_example_names())
def test_every_help_example_runs(name, tmp_path, tmp_path_factory, shared_results):
    """One test per command (and plot figure).  Every distinct example line runs from the
    state the lines before it leave: where another command's examples began with the same
    lines, from a copy of the folder they left (the same state, its lines run once)."""
    import shutil

    cwd = _outside_repository(tmp_path / name.replace(" ", "_"))
    lines = help_examples()[name]
    done = next((k for k in range(len(lines), 0, -1) if tuple(lines[:k]) in _HELP_STATES), 0)
    if done:
        shutil.copytree(_HELP_STATES[tuple(lines[:done])], cwd, symlinks=True)
    else:
        cwd.mkdir()
    shared = _shared_prefixes()
    for k, line in enumerate(lines[done:], done + 1):
        run_example_line(line, cwd)
        if tuple(lines[:k]) in shared:
            keep = tmp_path_factory.mktemp("help_state") / "d"
            shutil.copytree(cwd, keep, symlinks=True)
            _HELP_STATES[tuple(lines[:k])] = keep


def test_enough_help_examples_run():
    lines = [ln for name in _help_example_names() for ln in help_examples()[name]]
    assert sum(" view " not in f" {ln} " for ln in lines) >= 20


def test_collector_finds_blocks_and_markers(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("text\n\n<!-- docs-test: skip needs root -->\n```bash\nrm -rf /\n```\n\n"
                  "```python\nprint(1)\n```\n````\nnested ``` fence\n````\n")
    b = collect(md)
    assert [(x.lang, x.skip, x.line) for x in b] == [("bash", "needs root", 4),
                                                    ("python", None, 8), ("", None, 11)]
    assert b[1].code == "print(1)\n" and b[2].code == "nested ``` fence\n"


def test_docs_are_reference_not_a_diary():
    """docs/ says what is, not how it got there: history lives in CHANGELOG.md and
    benchmarks/results/ (issue 29)."""
    for doc in DOCS:
        text = doc.read_text()
        assert not re.search(r"session", text, re.I), f"{doc.relative_to(ROOT)} says 'session'"
        assert not re.search(r"\bround \d+\b", text, re.I), f"{doc.relative_to(ROOT)}: 'round N'"
    for name in ("throughput.md", "pipeline.md"):
        n = len((ROOT / "docs" / name).read_text().splitlines())
        assert n < 400, f"docs/{name} has {n} lines"
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert "## [Unreleased]" in changelog
