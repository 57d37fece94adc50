"""Environment variables set for a while and put back as they were."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable, Iterator


def restore_environ(saved: dict[str, str | None]) -> None:
    """Put the variables of ``saved`` back (None: unset)."""
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@contextlib.contextmanager
def saved_environ(keys: Iterable[str]) -> Iterator[Callable[[], None]]:
    """Context: the variables ``keys`` as they are on entry are put back on exit; the
    callable it yields puts them back earlier (e.g. once a child process has started
    with the values set inside).

    >>> with saved_environ(["MEMS_STEREO_EXAMPLE"]):
    ...     os.environ["MEMS_STEREO_EXAMPLE"] = "1"
    >>> "MEMS_STEREO_EXAMPLE" in os.environ
    False
    """
    saved = {k: os.environ.get(k) for k in keys}
    try:
        yield lambda: restore_environ(saved)
    finally:
        restore_environ(saved)
