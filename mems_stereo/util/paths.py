"""Input paths: refuse what cannot be read safely before opening it.

Every reader of the package opens its file through :func:`require_input_file`:
a missing path, a directory, a FIFO, a socket or a device is refused with one
:class:`~mems_stereo.errors.FormatError` naming the file, before ``open()``
(opening a FIFO would block forever waiting for a writer).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from mems_stereo.errors import FormatError

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"))


def file_kind(mode: int) -> str:
    """What a ``st_mode`` describes, in words ("a FIFO (named pipe)", "a regular file")."""
    for test, name in _KINDS:
        if test(mode):
            return name
    return "a regular file" if stat.S_ISREG(mode) else "not a regular file"


def require_input_file(path: str | os.PathLike, field: str | None = None) -> Path:
    """``path`` as a :class:`Path` if it is an existing, readable regular file.

    Raises :class:`FileNotFoundError` when it does not exist and
    :class:`~mems_stereo.errors.FormatError` (naming ``path`` and ``field``)
    when it is not a regular file or cannot be read.  Symbolic links are
    followed.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileNotFoundError(2, "file not found", str(p)) from None
    except OSError as e:
        raise FormatError(f"cannot access ({e.strerror})", source=str(p), field=field) from None
    if not stat.S_ISREG(st.st_mode):
        raise FormatError(f"expected a regular file, found {file_kind(st.st_mode)}",
                          source=str(p), field=field)
    if not os.access(p, os.R_OK):
        raise FormatError("cannot read the file (permission denied)", source=str(p), field=field)
    return p
