"""Inputs and outputs of a command run: checked before any work, committed together.

:class:`OutputPlan` is built from the command's arguments (:data:`IO` says
which arguments are inputs and outputs), before the command runs:

* every input must be an existing regular file (or folder where a folder is
  expected); a FIFO, a device or a directory in place of a file is refused;
* every output path is resolved and must differ from every input (also
  through symbolic or hard links) and from the other outputs, must not be an
  existing directory (or file, where a folder is written), its nearest
  existing ancestor must be a writable folder (not a file), its name must
  fit the file system, and its extension must be one the writer knows;
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
import secrets
import shutil
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.util.atomic import signals_blocked
from mems_stereo.util.paths import file_kind, require_input_file

CLOUD_SUFFIXES = (".ply", ".pcd", ".las", ".laz", ".mcap", ".db3")
PLOT_SUFFIXES = (".png", ".pdf", ".svg")


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
    "process": Spec({"recordings": "files", "system": "file"},
                    {"output": "cloud-or-dir", "labels": "h5", "histograms": "h5"}),
    "calibrate": Spec({"target_distances_file": "file", "recordings": "files",
                       "system": "system"}, {"output": "json", "report": "report"},
                      on_failure=("report",)),
    "import": Spec({"input": "file", "map": "file", "system": "system"}, {"output": "file"}),
    "samples": Spec({}, {"output": "dir"}),
    "export": Spec({"cloud": "file"}, {"output": "cloud"}),
    "view": Spec({"cloud": "file"}, {}),
    "render": Spec({"cloud": "file"}, {"output": "png"}),
    "plot acquisition": Spec({"system": "system"}, {"output": "plot"}),
    "plot histograms": Spec({"histograms": "file"}, {"output": "plot"}),
    "plot cloud": Spec({"cloud": "file"}, {"output": "plot"}),
    "demo": Spec({"samples": "dir"}, {"output": "dir"}),
}

_STACK: list[OutputPlan] = []
#: inputs given by an option (their errors name the option as well as the file)
_NAMED_INPUTS = ("system", "true_system", "target_distances_file")


def opt(name: str) -> str:
    """The option's name as typed (``output`` → ``-o/--output``, ``recordings`` → ``REC``)."""
    return {"output": "--output"}.get(name, "--" + name.replace("_", "-"))


def _preset_names() -> list[str]:
    """Every preset name a ``--system`` option takes (one- and two-axis)."""
    from mems_stereo.model.scanner2d import TWO_AXIS_PRESETS
    from mems_stereo.model.system import PRESETS

    return sorted(PRESETS) + sorted(TWO_AXIS_PRESETS)


def _is_preset(value: str) -> bool:
    return value in _preset_names()


def _real(p: Path) -> str:
    return os.path.realpath(os.path.abspath(p))


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


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

    # ---------------------------------------------------------------- checks

    def check(self) -> OutputPlan:
        """Check every input and output (raises before any work)."""
        a = self.args
        for name, kind in self.spec.inputs.items():
            v = getattr(a, name, None)
            if v is None:
                continue
            if kind == "files":
                for x in v:
                    self.inputs.append((name, require_input_file(x, None)))
            elif kind == "system" and _is_preset(str(v)):
                continue
            elif kind == "dir":
                p = Path(v)
                if not p.is_dir():
                    raise OptionError(f"expected a folder, found {self._what(p)}",
                                      source=str(p), field=opt(name))
                self.inputs.append((name, p))
            elif kind == "file" and Path(str(v)).suffix.lower() in (".mcap", ".db3") \
                    and Path(str(v)).with_suffix("").is_dir():
                self.inputs.append((name, Path(str(v)).with_suffix("")))  # a ROS 2 bag folder
            else:
                try:
                    self.inputs.append((name, require_input_file(v, None)))
                except FileNotFoundError:
                    if name not in _NAMED_INPUTS:
                        raise
                    if kind == "system":
                        import difflib

                        names = _preset_names()
                        close = difflib.get_close_matches(str(v), names, n=1, cutoff=0.5)
                        raise OptionError(
                            f"{v!r} is neither a preset nor a system file (file not found)\n"
                            + (f"did you mean {close[0]!r}? " if close else "")
                            + f"presets: {', '.join(names)}", field=opt(name)) from None
                    raise OptionError(f"expected an existing file, found {v!r} (file "
                                      "not found)", field=opt(name)) from None
        if self.command == "simulate":
            self.inputs += [("scene", m) for m in _scene_meshes(getattr(a, "scene", None))]
        if self.command == "demo" and getattr(a, "samples", None) is None:
            with contextlib.suppress(Exception):
                from mems_stereo.cli.demo import samples_dir

                self.inputs.append(("samples", samples_dir(None)))
        for name, kind in self.spec.outputs.items():
            v = getattr(a, name, None)
            if v is None:
                continue
            if kind == "cloud-or-dir":
                kind = "dir-of-clouds" if len(getattr(a, "recordings", [])) > 1 else "cloud"
            self.outputs.append((name, Path(v), kind))
        finals = {}
        for name, p, kind in self.outputs:
            self._check_output(name, p, kind)
            key = _real(p)
            if key in finals:
                raise OptionError(f"{p} is also the output of {opt(finals[key])}; "
                                  "expected distinct outputs", field=opt(name))
            finals[key] = name
            for member in self._members(p, kind):
                self._check_not_input(name, member, kind)
        return self

    @staticmethod
    def _what(p: Path) -> str:
        try:
            return file_kind(os.stat(p).st_mode)
        except OSError:
            return "nothing there"

    def _members(self, p: Path, kind: str) -> list[Path]:
        if kind == "dir-of-clouds":
            return [p, *(p / f"{Path(r).stem}.ply" for r in self.args.recordings)]
        return [p]

    def _check_not_input(self, name: str, p: Path, kind: str) -> None:
        key = _real(p)
        try:
            st = os.stat(p)
        except OSError:
            st = None
        for _iname, ip in self.inputs:
            same = key == _real(ip)
            if not same and st is not None:
                with contextlib.suppress(OSError):
                    ist = os.stat(ip)
                    same = (st.st_dev, st.st_ino) == (ist.st_dev, ist.st_ino)
            if kind == "dir" and not same:  # a folder written in place must not hold inputs
                same = key == _real(ip.parent) or key == _real(ip)
            if same:
                raise OptionError(f"{p} is an input of this run ({ip}); refusing to "
                                  "overwrite an input", field=opt(name))

    def _check_output(self, name: str, p: Path, kind: str) -> None:
        o = opt(name)
        if not str(p):
            raise OptionError("expected a file name, found an empty string", field=o)
        if len(os.fsencode(_real(p))) >= 4000:
            raise OptionError(f"path of {len(str(p))} characters is too long", field=o)
        try:
            st = os.stat(p)
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise OptionError(f"cannot use {p} ({e.strerror})", field=o) from None
        folder = kind in ("dir", "dir-of-clouds")
        if st is not None:
            if folder and not stat.S_ISDIR(st.st_mode):
                raise OptionError(f"{p} is {file_kind(st.st_mode)}, expected a folder", field=o)
            if not folder and not stat.S_ISREG(st.st_mode):
                raise OptionError(f"{p} is {file_kind(st.st_mode)}, expected a file to write",
                                  field=o)
        # the nearest existing ancestor must be a writable folder
        anc = Path(os.path.abspath(p)).parent
        while not anc.exists() and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            raise OptionError(f"cannot create {p}: {anc} is a file, not a folder", field=o)
        if not os.access(anc, os.W_OK | os.X_OK):
            raise OptionError(f"cannot write into {anc} (permission denied)", field=o)
        nmax = _name_max(anc)
        for part in Path(os.path.abspath(p)).parts:
            if len(os.fsencode(part)) > nmax - 40:
                raise OptionError(f"file name of {len(part)} characters is too long (the file "
                                  f"system allows {nmax}, less room for the temporary name)",
                                  field=o)
        sfx = p.suffix.lower()
        allowed = {"cloud": CLOUD_SUFFIXES, "png": (".png",), "plot": PLOT_SUFFIXES}.get(kind)
        if allowed and sfx not in allowed:
            raise OptionError(f"unknown extension {p.suffix!r} of {p}; expected one of "
                              f"{', '.join(allowed)}", field=o)
        if sfx == ".laz" and kind == "cloud":
            import laspy

            if not laspy.LazBackend.detect_available():
                raise OptionError("writing .laz needs a LAZ backend for laspy (pip install "
                                  "lazrs); use .las", field=o)

    # --------------------------------------------------------- stage / commit

    def stage(self) -> None:
        """Rewrite the output arguments to staged paths beside their targets (with the
        signals held back: every folder made is recorded in ``created`` for :meth:`abort`)."""
        with signals_blocked():
            self._stage()

    def _stage(self) -> None:
        for name, p, kind in self.outputs:
            if kind == "dir":  # written in place (demo): its steps commit their own outputs
                self._mkdirs(p)
                continue
            if kind == "cloud" and p.suffix.lower() in (".mcap", ".db3"):
                # a ROS 2 bag is a folder named after the output (room.mcap → room/), which
                # its writer fills and replaces itself: written in place, not staged
                self._mkdirs(p.parent)
                continue
            self._mkdirs(p.parent)
            tag = secrets.token_hex(4)
            staged = p.parent / f".{p.name[:60]}.ms-{tag}.part{p.suffix}"
            if kind == "dir-of-clouds":
                staged.mkdir()
                self.created.append(staged)
            self.staged[str(p)] = staged
            setattr(self.args, name, str(staged))
        self.state = "staged"

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
            from mems_stereo.cli._signals import committed

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
        """``text`` with staged paths replaced by the final ones."""
        for final, s in self.staged.items():
            text = text.replace(str(s), final)
        return text

    def names_staged(self, text: str) -> bool:
        return any(str(s) in text for s in self.staged.values())

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


def _scene_meshes(scene) -> list[Path]:
    """Mesh files a scene JSON names (best effort: the scene is validated later)."""
    if scene is None:
        return []
    try:
        from mems_stereo.util.jsonfile import read_json_file

        d = read_json_file(scene)
        base = Path(scene).parent
        return [base / o["file"] for o in d.get("objects", [])
                if isinstance(o, dict) and isinstance(o.get("file"), str)]
    except (FormatError, OSError, AttributeError, TypeError):
        return []
