"""The bundled sample data, found wherever the package is installed.

As ``skimage.data`` and ``open3d.data`` do::

    import mems_stereo as ms
    ms.data.list()                  # ['calib_1.5m.h5', ..., 'room.h5', 'room_scene.json']
    rec = ms.read_recording(ms.data.path("room.h5"))

The files are the repository's ``samples/`` folder (simulated recordings,
their scenes, the nominal and the true system, the calibration walls'
distances; see its README.md).  In a source checkout (also an editable
install) they are read from ``samples/`` beside the package; a built wheel
carries a copy as package data (``mems_stereo/data/samples/``).
"""

from __future__ import annotations

from pathlib import Path

from mems_stereo.errors import FormatError

__all__ = ["SAMPLE_SUFFIXES", "list", "path", "root"]

#: the kinds of files that are sample data (the generator script and README are not)
SAMPLE_SUFFIXES = (".h5", ".json", ".ptu")

_HERE = Path(__file__).resolve().parent


def _candidates() -> tuple[Path, ...]:
    # wheel: package data beside this module; source checkout: <repo>/samples
    return (_HERE / "samples", _HERE.parents[1] / "samples")


def root() -> Path:
    """The folder that holds the samples (absolute).

    Raises :class:`~mems_stereo.errors.FormatError` when the package was
    installed without its data.
    """
    for c in _candidates():
        if (c / "room.h5").is_file():
            return c
    raise FormatError("the sample data is not installed (looked in "
                      + ", ".join(map(str, _candidates())) + "); reinstall mems-stereo from "
                      "a wheel or a source checkout", field="mems_stereo.data")



def list() -> list[str]:  # noqa: A001 - the name skimage.data / open3d.data users expect
    """Names of the bundled sample files, sorted (``.h5`` recordings, ``.json`` files,
    ``.ptu`` time-tag files)."""
    return sorted(p.name for p in root().iterdir()
                  if p.is_file() and p.suffix in SAMPLE_SUFFIXES)


def path(name: str) -> Path:
    """Absolute path of the bundled sample ``name`` (e.g. ``"room.h5"``).

    Raises :class:`~mems_stereo.errors.FormatError` (a ``ValueError``) naming
    the available samples when there is no such file, with a suggestion for
    a near miss.
    """
    names = list()
    if name in names:
        return root() / name
    import difflib

    close = difflib.get_close_matches(str(name), names, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    raise FormatError(f"no sample named {name!r}; {hint}available: {', '.join(names)}",
                      field="mems_stereo.data.path")
