"""Atomic file output: nothing half-written is ever left behind.

Every writer of the package goes through :func:`atomic_output`: the data are
written to a temporary file in the target's directory and renamed over the
target only when the writer finished without error (``os.replace`` is atomic
on POSIX).  On an exception, including ``KeyboardInterrupt``, the temporary
file is removed and the target is left as it was.
"""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

#: signals held back while a temporary file is renamed or removed
_HELD = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))


_defer = {"depth": 0, "pending": None}


def deferring() -> bool:
    """True inside :func:`signals_blocked`: a signal handler should only record the
    signal (:func:`defer_signal`) and let the block finish."""
    return _defer["depth"] > 0


def defer_signal(signum: int) -> None:
    """Record a signal that arrived inside :func:`signals_blocked`; it is raised again
    (``signal.raise_signal``) when the outermost block ends."""
    if _defer["pending"] is None:
        _defer["pending"] = signum


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """Hold SIGINT/SIGTERM/SIGHUP back inside the block; they arrive when it ends.

    Used around renames and clean-ups, so that an interrupt cannot leave a
    half-committed set of outputs or a temporary file behind.  The signals are
    blocked for the main thread (``pthread_sigmask``) and, because another
    thread may still receive them, a handler that honours :func:`deferring`
    records them instead of raising; they are re-raised at the end.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # the depth first: from here on a handler that honours deferring() only records a
    # signal, so nothing below can be cut short between blocking and the try
    _defer["depth"] += 1
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
        try:
            yield
        finally:
            # unblocked while still deferring: a signal pending in the kernel is recorded
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
    finally:
        pending = None
        if _defer["depth"] == 1:
            pending, _defer["pending"] = _defer["pending"], None
        _defer["depth"] -= 1
        if pending is not None:
            signal.raise_signal(pending)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path to write; rename it to ``path`` on success.

    Parameters
    ----------
    path : target file.
    suffix : suffix of the temporary file (default: the target's), so that
        writers that pick the format from the extension (Open3D) still work.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    sfx = target.suffix if suffix is None else suffix
    tmp_path = None
    try:
        # created with the signals held back, inside the try: an interrupt can come
        # before the file exists or after tmp_path names it, never in between
        with signals_blocked():
            fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".part{sfx}",
                                       dir=target.parent)
            tmp_path = Path(tmp)
            os.close(fd)
        yield tmp_path
        with signals_blocked():
            um = os.umask(0)  # mkstemp makes 0600 files; give outputs the usual mode
            os.umask(um)
            os.chmod(tmp_path, 0o666 & ~um)
            os.replace(tmp_path, target)
    except BaseException:
        if tmp_path is not None:
            with signals_blocked(), contextlib.suppress(OSError):
                tmp_path.unlink()
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write text to ``path`` atomically; returns the path."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
