"""Documentation that cannot drift: every code block of README.md and docs/*.md and every
``--help`` example runs, from a temporary folder outside the repository, against the
installed package.

A small Markdown collector finds the fenced blocks (```lang ... ```).  How each runs:

* ``python``: as a script (``__name__ == "__main__"``, a fresh namespace) in this test
  process, cwd a fresh temporary folder; the blocks of one document run in order in the
  same folder.  The package and its libraries load once per test process, not once per
  block; a block that reads ``ms.NAME`` must find NAME in ``mems_stereo.__all__`` (what a
  fresh ``import mems_stereo`` gives).
* ``bash``, ``sh``, ``console`` and blocks without a language: line by line, each
  ``mems-stereo`` line through the CLI's ``main`` in this process (file-name patterns
  expanded as bash does) and any other line by ``bash -e -c`` with the interpreter's
  ``bin/`` first on PATH; the README's first line runs the installed ``mems-stereo``
  executable.  A block whose lines share shell state (``cd``, variables, compound
  commands, here-documents) runs whole by ``bash -e``.  The bundled walls' calibrations
  are memoised (tests/conftest.py ``shared_results``): each distinct call is fitted once
  per test process, by the real function, and the blocks and ``mems-stereo demo``'s test
  share it.
* ``json``: parsed (``json.loads``); nothing else.
* Indented (4-space) blocks are read as literal text — output listings, package
  lists — and not run; every command a reader is meant to type is in a fenced block.
* A block right after a line ``<!-- docs-test: skip REASON -->`` does not run; the test
  prints each with its reason.  The only such blocks are the README's two set-up
  commands (they install Debian packages as root and build ``.venv`` in the repository),
  its command that builds the API reference into the repository (tests/test_api_reference.py
  builds it on its own, with the ``stress`` marker), and the C++ reader of docs/interchange.md.

The ``--help`` examples (each command module's ``EXAMPLE`` lines and ``plot``'s per-figure
examples) run in order in a fresh folder per command, in this process through the CLI's
``main`` (each line as a process of its own paid the package's import again; the
``mems-stereo`` executable runs in the README's first line and tests/test_wheel.py); lines
that several commands' examples begin with run once, and the other commands continue from a copy of the folder
they left (the same state); ``view`` opens a window, so its last line is only parsed;
``demo``'s example is the run of ``tests/test_demo.py``.

``tests/test_wheel.py`` (``stress`` marker: ``pytest -m stress``) builds a wheel and
processes a bundled sample with that non-editable install.
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


SHELL_LANGS = ("", "bash", "sh", "console", "shell")
#: seconds a python block's non-daemon threads may run on after its last line
THREAD_GRACE_S = 30.0
#: a line starting with one of these changes the shell's state (or spans lines): its block
#: runs as one ``bash -e`` script
_STATEFUL = {"cd", "export", "source", ".", "set", "unset", "alias", "pushd", "popd", "shopt",
             "function", "if", "for", "while", "until", "case", "select", "{", "(", "trap",
             "exec", "eval", "declare", "local", "readonly"}


def shell_lines(code: str) -> list[str]:
    """The logical lines of a shell block (backslash continuations joined), blank ones
    dropped."""
    out, cur = [], ""
    for line in code.splitlines():
        if line.rstrip().endswith("\\"):
            cur += line.rstrip()[:-1] + " "
            continue
        if (cur + line).strip():
            out.append((cur + line).strip())
        cur = ""
    if cur.strip():
        out.append(cur.strip())
    return out


def _tokens(line: str) -> list[str] | None:
    """The words of one shell line with its operators as tokens of their own, comments
    dropped; None where shlex cannot split it (unbalanced quotes)."""
    lex = shlex.shlex(line, posix=True, punctuation_chars=True)
    lex.whitespace_split = True
    try:
        return list(lex)
    except ValueError:
        return None


def split_is_faithful(lines: list[str]) -> bool:
    """Running the lines one by one (each ``mems-stereo`` line in this process, any other
    as ``bash -e -c LINE``) does what ``bash -e`` does with the block: no line sets state a
    later line reads (``cd``, variables, functions), none spans lines, none is a compound
    command; a here-document or an unbalanced quote keeps the block whole."""
    ops = {";", "&&", "||", "|", "&"}
    for line in lines:
        tok = _tokens(line)
        if tok == []:  # a comment
            continue
        if tok is None or "<<" in line or tok[-1] in ops | {"("}:
            return False
        # the command words: the first, and each after an operator
        words = [tok[0]] + [t for p, t in zip(tok, tok[1:]) if p in ops]
        if any(w in _STATEFUL or re.match(r"\w+=", w) for w in words):
            return False
    return True


def in_process_argv(line: str, cwd: Path) -> list[str] | None:
    """``mems-stereo``'s arguments when ``line`` is one plain ``mems-stereo`` command (no
    operator, redirection, expansion but a file-name pattern, which is expanded here in
    ``cwd`` as bash does); None otherwise."""
    import glob

    tok = _tokens(line)
    if not tok or tok[0] != "mems-stereo" or "$" in line or "`" in line:
        return None
    if any(set(t) <= set("();<>|&") for t in tok):
        return None
    argv = []
    for t in tok[1:]:
        hits = sorted(glob.glob(t, root_dir=cwd)) if glob.has_magic(t) else []
        argv.extend(hits or [t])
    return argv


def run_cli(argv: list[str], cwd: Path, what: str) -> None:
    """``mems-stereo ARGV`` run in this process by the CLI's ``main`` from ``cwd``; fails
    with ``what`` and the command's output unless it exits 0.  ``view`` opens a window:
    its arguments are parsed, not run."""
    import contextlib
    import io
    import traceback

    from mems_stereo.cli import build_parser, main

    if argv[0] == "view":
        build_parser().parse_args(argv)
        return
    out, err, here = io.StringIO(), io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv)
    except SystemExit as e:  # usage errors (argparse)
        rc = e.code
    except Exception:
        rc = "exception\n" + traceback.format_exc()
    finally:
        os.chdir(here)
    if rc != 0:
        pytest.fail(f"{what}: exit {rc}\n--- stdout\n{out.getvalue()[-3000:]}\n--- stderr\n"
                    f"{err.getvalue()[-3000:]}")


def run_python_block(block: Block, cwd: Path, where: str) -> None:
    """A python block executed in this process as a script (``__name__ == "__main__"``, a
    fresh namespace, cwd ``cwd``); fails with its place, traceback and output.  The
    package and the libraries are imported once per test process instead of once per
    block; ``mems_stereo``'s attributes that a block reads are checked to be ones a fresh
    ``import mems_stereo`` gives (:func:`package_names_used`)."""
    import contextlib
    import io
    import threading
    import traceback

    import mems_stereo

    missing = package_names_used(block.code) - set(mems_stereo.__all__) - {"__version__"}
    if missing:
        pytest.fail(f"{where}: reads {sorted(missing)} of mems_stereo, which a fresh "
                    "`import mems_stereo` does not give (not in mems_stereo.__all__)")
    code = compile(block.code, where, "exec")
    out, err, here = io.StringIO(), io.StringIO(), os.getcwd()
    before = set(threading.enumerate())
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            exec(code, {"__name__": "__main__", "__builtins__": __builtins__})
    except BaseException as e:  # SystemExit(0) is a success, as for a script
        if not (isinstance(e, SystemExit) and e.code in (0, None)):
            pytest.fail(f"{where} failed:\n{block.code}\n{traceback.format_exc()[-3000:]}\n"
                        f"--- stdout\n{out.getvalue()[-3000:]}\n--- stderr\n"
                        f"{err.getvalue()[-3000:]}")
    finally:
        os.chdir(here)
    # a script ends when its last non-daemon thread does: one still running long after
    # the block's end would hang the reader's interpreter
    for t in set(threading.enumerate()) - before:
        t.join(THREAD_GRACE_S if not t.daemon else 0.0)
        if t.is_alive() and not t.daemon:
            pytest.fail(f"{where}: its thread {t.name} still runs {THREAD_GRACE_S} s after "
                        "the block's end")


def package_names_used(code: str) -> set[str]:
    """Names read as ``alias.NAME`` where ``alias`` is bound by ``import mems_stereo`` /
    ``import mems_stereo as alias`` in ``code``."""
    import ast

    tree = ast.parse(code)
    aliases = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.Import)
               for a in n.names if a.name == "mems_stereo"}
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
            and isinstance(n.value, ast.Name) and n.value.id in aliases}


def run_block(block: Block, cwd: Path, python: str = sys.executable,
              executable_lines: int = 0) -> None:
    """Execute one block in ``cwd``; fail with the block's place and output.

    Python blocks run in this process (:func:`run_python_block`).  A shell block whose
    lines can run one by one (:func:`split_is_faithful`) runs its ``mems-stereo`` lines in
    this process (:func:`run_cli`), except its first ``executable_lines`` lines, and every
    other line by ``bash -e -c`` with the interpreter's ``bin/`` first on PATH (the
    installed ``mems-stereo``); any other shell block runs whole by ``bash -e``."""
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
        run_python_block(block, cwd, where)
        return
    if block.lang not in SHELL_LANGS:
        pytest.fail(f"{where}: no rule to run a {block.lang!r} block (add one or a skip marker)")
    lines = shell_lines(block.code)
    if not split_is_faithful(lines):
        _run_bash(block.code, cwd, python, where)
        return
    lines = [ln for ln in lines if _tokens(ln)]  # comments do nothing
    for k, line in enumerate(lines):
        argv = in_process_argv(line, cwd) if k >= executable_lines else None
        if argv is None:
            _run_bash(line, cwd, python, f"{where}, line {line!r}")
        else:
            run_cli(argv, cwd, f"{where}: {line}")


def _run_bash(code: str, cwd: Path, python: str, where: str) -> None:
    p = subprocess.run(["bash", "-e", "-c", code], cwd=cwd, env=_env(python),
                       capture_output=True, text=True, timeout=600)
    if p.returncode:
        pytest.fail(f"{where} failed (exit {p.returncode}):\n{code}\n--- stdout\n"
                    f"{p.stdout[-3000:]}\n--- stderr\n{p.stderr[-3000:]}")


def _outside_repository(tmp_path: Path) -> Path:
    assert ROOT not in tmp_path.resolve().parents, "the temporary folder is in the repository"
    return tmp_path


# the documents whose blocks calibrate the bundled walls run in the pytest-xdist worker of
# tests/conftest.py's "bundled_calibrations" group: their fits are the demo's
# (``shared_results``: one real fit per distinct call and test process)
@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCS, ids=lambda d: d.name)
def test_every_code_block_of_the_docs_runs(doc, tmp_path, shared_results):
    """One test per document, so that pytest-xdist spreads the documents over the cores.
    The README's first shell line runs the installed ``mems-stereo`` executable (as
    tests/test_wheel.py does from a wheel); the other ``mems-stereo`` lines run in this
    process (:func:`run_block`)."""
    cwd = _outside_repository(tmp_path / doc.stem)
    cwd.mkdir()
    executable_lines = int(doc.name == "README.md")
    for b in collect(doc):
        if b.skip is None:
            run_block(b, cwd, executable_lines=executable_lines)
            if b.lang in SHELL_LANGS:
                executable_lines = 0


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
    ``cwd`` (:func:`run_cli`; the entry point itself, a separate process, is run by the
    README's first line in :func:`test_every_code_block_of_the_docs_runs` and by
    tests/test_wheel.py); fails with the line and its output unless it exits 0.  ``view``
    opens a window: parsed only."""
    argv = shlex.split(line, comments=True)
    assert argv[0] == "mems-stereo", line
    run_cli(argv[1:], cwd, line)


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


def test_shell_blocks_split_only_where_faithful(tmp_path):
    """A shell block runs line by line (``mems-stereo`` lines in this process) only where
    that is what ``bash -e`` does with it."""
    code = ("# set up\nmems-stereo samples -o samples   # all of them\n"
            "mems-stereo calibrate samples/c_*.h5 \\\n    -o cal.json\npython -c 'print(1)'\n")
    lines = shell_lines(code)
    assert lines == ["# set up", "mems-stereo samples -o samples   # all of them",
                     "mems-stereo calibrate samples/c_*.h5      -o cal.json",
                     "python -c 'print(1)'"]
    assert split_is_faithful(lines)
    for whole in ("cd out\nmems-stereo info x.h5", "X=1\necho $X", "mems-stereo info a && cd b",
                  "for f in *.h5; do\n  mems-stereo info $f\ndone", "cat <<EOF\nx\nEOF",
                  "mems-stereo info 'a"):
        assert not split_is_faithful(shell_lines(whole)), whole
    (tmp_path / "samples").mkdir()
    for name in ("c_2.h5", "c_1.h5"):
        (tmp_path / "samples" / name).touch()
    assert in_process_argv(lines[2], tmp_path) == [
        "calibrate", "samples/c_1.h5", "samples/c_2.h5", "-o", "cal.json"]
    assert in_process_argv(lines[1], tmp_path) == ["samples", "-o", "samples"]
    for shell in ("python -c 'print(1)'", "mems-stereo info a.h5 > out.txt",
                  "mems-stereo info a.h5 | head", "mems-stereo info $F", "mems-stereo info a; ls"):
        assert in_process_argv(shell, tmp_path) is None, shell


def test_a_broken_block_fails(tmp_path, monkeypatch):
    """Each way of running a block fails the test when the block fails, naming its place."""
    monkeypatch.setattr(sys.modules[__name__], "THREAD_GRACE_S", 0.1)
    doc = ROOT / "README.md"
    broken = [("python", "import numpy\nnumpy.no_such_function()\n"),
              ("python", "import mems_stereo as ms\nms.pipeline\n"),  # not what a fresh import gives
              ("python", "import sys\nsys.exit(3)\n"),
              ("python", "import threading, time\n"  # would not let the interpreter exit
                         "threading.Thread(target=time.sleep, args=(1,)).start()\n"),
              ("bash", "mems-stereo samples -o s room.h5\nmems-stereo process s/no_such.h5 -o x.ply\n"),
              ("bash", "mems-stereo no-such-command\n"),
              ("bash", "true\nfalse\n"),
              ("bash", "cd .\nmems-stereo process no_such.h5 -o x.ply\n"),  # whole, by bash
              ("json", "{1: 2}\n")]
    for k, (lang, code) in enumerate(broken):
        cwd = tmp_path / str(k)
        cwd.mkdir()
        with pytest.raises(pytest.fail.Exception, match=r"README\.md:7 "):
            run_block(Block(doc, 7, lang, code, None), cwd)
    for lang, code in (("python", "import sys\nprint('ok')\nsys.exit(0)\n"),
                       ("bash", "mems-stereo samples -o s room.h5\ntest -s s/room.h5\n")):
        run_block(Block(doc, 7, lang, code, None), tmp_path)


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
