"""Inputs and outputs of a command run: checked before any work, committed together.

:class:`OutputPlan` is built from the command's arguments (:data:`IO` says
which arguments are inputs and outputs), before the command runs:

* every input and output passes the checks of :mod:`mems_stereo.cli._pathcheck`
  (inputs exist and are regular files; outputs are not inputs, are distinct,
  writable, with names that fit and extensions the writers know);
* the command then writes each output to a *staged* path beside the target
  (``.NAME.ms-XXXXXXXX.part.EXT``): the arguments are rewritten to the staged
  paths, so the command's own code is unchanged;
* :meth:`OutputPlan.commit` renames every staged output over its target at the
  end, with SIGINT/SIGTERM/SIGHUP held back: all outputs of a run appear
  together or none does; :meth:`OutputPlan.abort` removes the staged files
  and the folders the run created.

Printed lines that name a staged path are shown with the final path and only
once the outputs are committed (:func:`emit`), so the tool never says
"wrote X" for an output that was then discarded.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

from mems_stereo.cli._pathcheck import check_outputs, opt, resolve_inputs, resolve_outputs
from mems_stereo.cli._signals import committed
from mems_stereo.errors import OptionError
from mems_stereo.util.atomic import signals_blocked


@dataclass(frozen=True)
class Spec:
    """Inputs and outputs of one command: argument name → kind.

    Input kinds: ``file``, ``files`` (a list), ``system`` (a file or a preset
    name), ``dir``.  Output kinds: ``cloud``, ``png``, ``plot``, ``h5``,
    ``json``, ``cloud-or-dir`` (a folder when several recordings are given),
    ``dir`` (written in place, see ``demo``).
    """

    inputs: dict = field(default_factory=dict)
    outputs: dict = field(default_factory=dict)
    #: outputs committed even when the command fails (diagnostics such as a report)
    on_failure: tuple = ()


#: commands (``plot`` by figure) → their inputs and outputs
IO: dict[str, Spec] = {
    "info": Spec({"system": "system"}, {"plot": "plot"}),
    "simulate": Spec({"scene": "file", "system": "system", "true_system": "system"},
                     {"output": "h5"}),
    "process": Spec({"recordings": "files", "system": "system"},
                    {"output": "cloud-or-dir", "labels": "h5", "histograms": "h5"}),
    "calibrate": Spec({"target_distances_file": "file", "recordings": "files",
                       "system": "system"}, {"output": "json", "report": "report"},
                      on_failure=("report",)),
    "import": Spec({"input": "file", "map": "file", "system": "system"}, {"output": "file"}),
    "samples": Spec({}, {"output": "dir"}),
    "export": Spec({"cloud": "file"}, {"output": "cloud"}),
    "view": Spec({"cloud": "file"}, {}),
    "render": Spec({"cloud": "file", "system": "system"}, {"output": "png"}),
    "plot acquisition": Spec({"system": "system"}, {"output": "plot"}),
    "plot histograms": Spec({"histograms": "file"}, {"output": "plot"}),
    "plot cloud": Spec({"cloud": "file"}, {"output": "plot"}),
    "demo": Spec({"samples": "dir"}, {"output": "dir"}),
    "live": Spec({"replay": "file", "system": "system", "map": "file"}, {"output": "frames"}),
}

_STACK: list[OutputPlan] = []


class OutputPlan:
    """The checked inputs and the staged outputs of one command run."""

    def __init__(self, command: str, args):
        self.command = command
        self.args = args
        self.spec = IO.get(command, Spec({}, {"output": "file"} if hasattr(args, "output")
                                          else {}))
        self.inputs: list[tuple[str, Path]] = []
        self.outputs: list[tuple[str, Path, str]] = []   # (arg, final, kind)
        self.staged: dict[str, Path] = {}                # final str → staged
        self.created: list[Path] = []
        self.committed: list[Path] = []
        self.buffer: list[str] = []
        self.state = "planned"

    def check(self) -> OutputPlan:
        """Check every input and output (raises before any work)."""
        self.inputs = resolve_inputs(self.command, self.spec.inputs, self.args)
        self.outputs = resolve_outputs(self.spec.outputs, self.args)
        check_outputs(self.outputs, self.inputs, getattr(self.args, "recordings", ()),
                      self.command, bool(getattr(self.args, "parents", False)))
        return self

    # --------------------------------------------------------- stage / commit

    def stage(self) -> None:
        """Rewrite the output arguments to staged paths beside their targets (with the
        signals held back: every folder made is recorded in ``created`` for :meth:`abort`)."""
        with signals_blocked():
            self._stage()

    def _stage(self) -> None:
        for name, p, kind in self.outputs:
            try:
                self._stage_one(name, p, kind)
            except OSError as e:  # e.g. a virtual file system that refuses new files
                where = "" if e.filename is None or self.names_staged(str(e.filename)) \
                    else f" at {e.filename}"  # a folder on the way
                raise OptionError(f"cannot write {p} ({e.strerror or type(e).__name__}"
                                  f"{where})", field=opt(name)) from None
        self.state = "staged"

    def _stage_one(self, name: str, p: Path, kind: str) -> None:
        if kind == "dir":  # written in place (demo): its steps commit their own outputs
            self._mkdirs(p)
            return
        if kind == "cloud" and p.suffix.lower() in (".mcap", ".db3"):
            # a ROS 2 bag is a folder named after the output (room.mcap → room/), which
            # its writer fills and replaces itself: written in place, not staged
            self._mkdirs(p.parent)
            return
        self._mkdirs(p.parent)
        tag = secrets.token_hex(4)
        staged = p.parent / f".{p.name[:60]}.ms-{tag}.part{p.suffix}"
        self.staged[str(p)] = staged
        setattr(self.args, name, str(staged))
        if kind == "dir-of-clouds":
            staged.mkdir()
            self.created.append(staged)
        else:  # a folder can look writable and take no new file (/proc and the like)
            os.close(os.open(staged, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            os.unlink(staged)

    def _mkdirs(self, d: Path) -> None:
        missing = []
        while not d.exists():
            missing.append(d)
            d = d.parent
        for m in reversed(missing):
            m.mkdir()
            self.created.append(m)

    def commit(self, names=None) -> list[Path]:
        """Move every staged output (or those of the arguments ``names``) onto its
        target (signals held back meanwhile)."""
        with signals_blocked():
            for _name, p, kind in self.outputs:
                if names is not None and _name not in names:
                    continue
                s = self.staged.get(str(p))
                if s is None:
                    continue
                if kind == "dir-of-clouds":
                    p.mkdir(exist_ok=True)
                    for f in sorted(s.iterdir()):
                        os.replace(f, p / f.name)
                        self.committed.append(p / f.name)
                    s.rmdir()
                    self.created.remove(s)
                elif s.exists():
                    os.replace(s, p)
                    self.committed.append(p)
            # a partial commit (a failed run's diagnostics): the rest is aborted on exit
            self.state = "committed" if names is None else "partial"
            committed(self.committed)
        return self.committed

    def abort(self) -> None:
        """Remove the staged outputs and the folders this run created."""
        with signals_blocked():
            for s in self.staged.values():
                with contextlib.suppress(OSError):
                    if s.is_dir():
                        shutil.rmtree(s)
                    else:
                        s.unlink()
            for d in reversed(self.created):
                with contextlib.suppress(OSError):
                    d.rmdir()  # only if empty
            self.state = "aborted"
            self.buffer.clear()

    # ------------------------------------------------------------- messages

    def translate(self, text: str) -> str:
        """``text`` with staged paths, and the writers' temporary files beside them
        (``<folder>/.<staged name>.<random>.part<ext>``), replaced by the final ones."""
        for final, s in self.staged.items():
            stem = s.name[: -len(s.suffix)] if s.suffix else s.name
            temp = re.compile(re.escape(str(s.parent)) + r"/\.?" + re.escape(stem)
                              + r"[^\s:'\"]*")
            text = temp.sub(lambda _m, f=final: f, text.replace(str(s), final))
        return text

    def names_staged(self, text: str) -> bool:
        return self.translate(text) != text

    def option_of(self, text: str) -> str | None:
        """The option (``--output``…) whose staged output ``text`` names, if any."""
        named = self.translate(text)
        for name, p, _kind in self.outputs:
            if str(p) in self.staged and named.startswith(str(p)):
                return opt(name)
        return None

    def __enter__(self) -> OutputPlan:
        _STACK.append(self)
        return self

    def __exit__(self, exc_type, exc, tb):
        _STACK.remove(self)
        if self.state != "committed":
            self.abort()
        else:
            for line in self.buffer:
                emit(line)
        self.buffer = []
        return False


def emit(msg: str, file=None) -> None:
    """Print ``msg``; a line naming a staged output waits until it is committed."""
    for plan in reversed(_STACK):
        if plan.names_staged(msg):
            plan.buffer.append(plan.translate(msg))
            return
    print(msg, file=file or sys.stdout)


def translate(text: str) -> str:
    """``text`` with every active plan's staged paths replaced by the final ones."""
    for plan in reversed(_STACK):
        text = plan.translate(text)
    return text
