"""The checks a command's paths pass before any work (used by :class:`OutputPlan`).

* every input must be an existing regular file (or folder where a folder is
  expected); a FIFO, a device or a directory in place of a file is refused;
* every output path must differ from every input (also through symbolic or
  hard links) and from the other outputs, must not be an existing directory
  (or file, where a folder is written), its nearest existing ancestor must
  be a writable folder (not a file), its name must fit the file system
  (with room for the staged name), its folder must exist (unless
  ``--parents``: then the missing folders are made, as ``mkdir -p``; a folder
  output may itself be new, its parent must exist), and its suffix must be
  one the command writes (:data:`mems_stereo.cli._writes.WRITES`).

Each check raises :class:`~mems_stereo.errors.OptionError` naming the option.
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path

from mems_stereo import data
from mems_stereo.cli._writes import CLOUD_SUFFIXES, PLOT_SUFFIXES, WRITES, frames_to_folder
from mems_stereo.errors import FormatError, OptionError
from mems_stereo.model.presets import UnknownPresetError, system_source
from mems_stereo.util.jsonfile import read_json_file
from mems_stereo.util.paths import file_kind, require_input_file

#: inputs given by an option (their errors name the option as well as the file)
_NAMED_INPUTS = ("system", "true_system", "target_distances_file")


def opt(name: str) -> str:
    """The option's name as typed (``output`` → ``-o/--output``, ``recordings`` → ``REC``)."""
    return {"output": "--output"}.get(name, "--" + name.replace("_", "-"))


def samples_dir(explicit=None) -> Path:
    """The sample folder: ``explicit``, else the bundled samples (:mod:`mems_stereo.data`)."""
    if not explicit:
        return data.root()
    c = Path(explicit)
    if not (c / "room.h5").exists():
        raise FormatError(f"no sample recordings in {c} (expected room.h5 there)\n"
                          "leave --samples out to use the bundled ones", field="--samples")
    return c


def _real(p: Path) -> str:
    return os.path.realpath(os.path.abspath(p))


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def describe(p: Path) -> str:
    """What is at ``p`` in words ("a folder", "a FIFO", "nothing there")."""
    try:
        return file_kind(os.stat(p).st_mode)
    except OSError:
        return "nothing there"


# ------------------------------------------------------------------ inputs

def _missing_named_input(name: str, v) -> OptionError:
    """The error for a ``--target-distances-file`` (``--system``: see :func:`_system_path`)
    value that is no file."""
    return OptionError(f"expected an existing file, found {v!r} (file not found)",
                       field=opt(name))


def _system_path(name: str, v) -> list[Path]:
    """A ``--system`` value through the one resolution of every command
    (:func:`~mems_stereo.model.presets.system_source`): an existing file (checked),
    else a preset (no path), else the error naming the option."""
    try:
        src = system_source(v)
    except UnknownPresetError as e:
        raise OptionError(str(e), field=opt(name)) from None
    return [] if isinstance(src, str) else [require_input_file(src, None)]


#: positional arguments (named as such in messages, not as ``--options``)
_POSITIONAL = ("recordings", "scene", "cloud", "histograms", "input")


def _refuse_empty(name: str, v) -> None:
    """An empty path would mean the working folder ("."): refused naming the argument."""
    if isinstance(v, (str, os.PathLike)) and not os.fspath(v).strip():
        raise OptionError("expected a file name, found an empty string",
                          field=name if name in _POSITIONAL else opt(name))


def _input_paths(name: str, kind: str, v) -> list[Path]:
    """The checked path(s) of one input argument (none for a preset name)."""
    for x in (v if kind == "files" else [v] if kind != "system" else []):
        _refuse_empty(name, x)
    if kind == "files":
        paths = [require_input_file(x, None) for x in v]
        _refuse_repeated(name, paths)
        return paths
    if kind == "system":
        return _system_path(name, v)
    if kind == "dir":
        p = Path(v)
        if not p.is_dir():
            raise OptionError(f"expected a folder, found {describe(p)}", source=str(p),
                              field=opt(name))
        return [p]
    if kind == "file" and Path(str(v)).suffix.lower() in (".mcap", ".db3") \
            and Path(str(v)).with_suffix("").is_dir():
        return [Path(str(v)).with_suffix("")]  # a ROS 2 bag folder
    try:
        return [require_input_file(v, None)]
    except FileNotFoundError:
        if name not in _NAMED_INPUTS:
            raise
        raise _missing_named_input(name, v) from None


def _identity(p: Path):
    with contextlib.suppress(OSError):
        st = os.stat(p)
        return (st.st_dev, st.st_ino)
    return _real(p)


def _refuse_repeated(name: str, paths: list[Path]) -> None:
    """The same file given twice (also through a link) would count its data twice."""
    seen: dict = {}
    for p in paths:
        key = _identity(p)
        if key in seen:
            also = "" if str(seen[key]) == str(p) else f" (as {seen[key]})"
            raise OptionError(f"{p} is given twice{also}; expected each recording once",
                              field=opt(name))
        seen[key] = p


def resolve_inputs(command: str, inputs: dict, args) -> list[tuple[str, Path]]:
    """Every input path of a run as ``(argument, path)``, each checked to exist.

    ``inputs`` maps argument name → kind (``file``, ``files``, ``system``,
    ``dir``); the meshes a ``simulate`` scene names and the sample folder
    ``demo`` reads count as inputs too (so no output may overwrite them).
    """
    out: list[tuple[str, Path]] = []
    for name, kind in inputs.items():
        v = getattr(args, name, None)
        if v is not None:
            out += [(name, p) for p in _input_paths(name, kind, v)]
    if command == "simulate":
        out += [("scene", m) for m in _scene_meshes(getattr(args, "scene", None))]
    if command == "demo" and getattr(args, "samples", None) is None:
        with contextlib.suppress(Exception):
            out.append(("samples", samples_dir(None)))
    return out


def _scene_meshes(scene) -> list[Path]:
    """Mesh files a scene JSON names (best effort: the scene is validated later)."""
    if scene is None:
        return []
    try:
        d = read_json_file(scene)
        base = Path(scene).parent
        return [base / o["file"] for o in d.get("objects", [])
                if isinstance(o, dict) and isinstance(o.get("file"), str)]
    except (FormatError, OSError, AttributeError, TypeError):
        return []


# ----------------------------------------------------------------- outputs

def resolve_outputs(outputs: dict, args) -> list[tuple[str, Path, str]]:
    """Every output of a run as ``(argument, path, kind)``; ``cloud-or-dir``
    becomes ``dir-of-clouds`` when several recordings are given, else ``cloud``."""
    out = []
    for name, kind in outputs.items():
        v = getattr(args, name, None)
        if v is None:
            continue
        _refuse_empty(name, v)
        if kind == "frames":  # live -o: a folder (DIR/, or one that exists) or a bag
            kind = "dir" if str(v).endswith(("/", os.sep)) or os.path.isdir(v) else "cloud"
        if kind == "cloud-or-dir":
            many = len(getattr(args, "recordings", [])) > 1 or frames_to_folder(args)
            kind = "dir-of-clouds" if many else "cloud"
        out.append((name, Path(v), kind))
    return out


def check_outputs(outputs: list, inputs: list, recordings=(), command: str | None = None,
                  parents: bool = False) -> None:
    """Check every output path, that they are distinct and that none is an input
    (``command``: the suffixes it writes are checked; ``parents``: ``--parents``)."""
    finals: dict[str, str] = {}
    for name, p, kind in outputs:
        check_output_path(name, p, kind, command, parents)
        key = _real(p)
        if key in finals:
            raise OptionError(f"{p} is also the output of {opt(finals[key])}; "
                              "expected distinct outputs", field=opt(name))
        finals[key] = name
        members = [p]
        if kind == "dir-of-clouds":
            clouds = [p / f"{Path(r).stem}.ply" for r in recordings]
            for i, c in enumerate(clouds):
                if c in clouds[:i]:
                    raise OptionError(f"{recordings[clouds.index(c)]} and {recordings[i]} "
                                      f"would both be written to {c}; expected recordings "
                                      "with distinct file names", field=opt(name))
            members += clouds
        for member in members:
            check_not_input(name, member, kind, inputs)


def check_not_input(name: str, p: Path, kind: str, inputs: list) -> None:
    """Refuse an output ``p`` that is one of ``inputs`` (by path or by inode);
    a folder written in place (``kind == "dir"``) must not hold an input either."""
    key = _real(p)
    try:
        st = os.stat(p)
    except OSError:
        st = None
    for _iname, ip in inputs:
        same = key == _real(ip)
        if not same and st is not None:
            with contextlib.suppress(OSError):
                ist = os.stat(ip)
                same = (st.st_dev, st.st_ino) == (ist.st_dev, ist.st_ino)
        if kind == "dir" and not same:
            same = key == _real(ip.parent) or key == _real(ip)
        if same:
            raise OptionError(f"{p} is an input of this run ({ip}); refusing to "
                              "overwrite an input", field=opt(name))


def _check_existing(o: str, p: Path, folder: bool) -> None:
    """What already exists at ``p`` must be of the kind written there."""
    try:
        st = os.stat(p)
    except FileNotFoundError:
        return
    except OSError as e:
        raise OptionError(f"cannot use {p} ({e.strerror})", field=o) from None
    if folder and not stat.S_ISDIR(st.st_mode):
        raise OptionError(f"{p} is {file_kind(st.st_mode)}, expected a folder", field=o)
    if not folder and not stat.S_ISREG(st.st_mode):
        raise OptionError(f"{p} is {file_kind(st.st_mode)}, expected a file to write",
                          field=o)


def _check_writable_place(o: str, p: Path, parents: bool = False) -> None:
    """The nearest existing ancestor is a writable folder (without ``parents``: the
    output's own folder); every name fits."""
    anc = Path(os.path.abspath(p)).parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise OptionError(f"cannot create {p}: {anc} is a file, not a folder", field=o)
    if not parents and anc != Path(os.path.abspath(p)).parent:
        raise OptionError(f"folder {p.parent} does not exist; create it or give --parents "
                          "(mkdir -p)", field=o)
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OptionError(f"cannot write into {anc} (permission denied)", field=o)
    nmax = _name_max(anc)
    for part in Path(os.path.abspath(p)).parts:
        if len(os.fsencode(part)) > nmax - 40:
            raise OptionError(f"file name of {len(part)} characters is too long (the file "
                              f"system allows {nmax}, less room for the temporary name)",
                              field=o)


def _check_extension(o: str, p: Path, kind: str, allowed: tuple | None = None) -> None:
    """``p``'s suffix is one of ``allowed`` (default: those of the output ``kind``)."""
    sfx = p.suffix.lower()
    if allowed is None:
        allowed = {"cloud": CLOUD_SUFFIXES, "png": (".png",), "plot": PLOT_SUFFIXES}.get(kind)
    if kind in ("dir", "dir-of-clouds"):
        return  # a folder: no suffix
    if allowed and sfx not in allowed:
        what = f"unknown extension {p.suffix!r} of" if p.suffix else "no extension on"
        raise OptionError(f"{what} {p}; expected one of {', '.join(allowed)}", field=o)
    if sfx == ".laz" and kind == "cloud":
        import laspy

        if not laspy.LazBackend.detect_available():
            raise OptionError("writing .laz needs a LAZ backend for laspy (pip install "
                              "lazrs); use .las", field=o)


def check_output_path(name: str, p: Path, kind: str, command: str | None = None,
                      parents: bool = False) -> None:
    """Check one output path of argument ``name`` of ``command`` before any work (see
    module doc)."""
    o = opt(name)
    if not str(p):
        raise OptionError("expected a file name, found an empty string", field=o)
    if len(os.fsencode(_real(p))) >= 4000:
        raise OptionError(f"path of {len(str(p))} characters is too long", field=o)
    _check_existing(o, p, folder=kind in ("dir", "dir-of-clouds"))
    _check_writable_place(o, p, parents)
    written = WRITES.get((command, name))
    _check_extension(o, p, kind, written.suffixes if written is not None else None)
