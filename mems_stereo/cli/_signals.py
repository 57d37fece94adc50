"""SIGINT, SIGTERM and SIGHUP during a command: clean up, exit 128 + signal, say what was kept.

:func:`signal_guard` installs one handler for the three signals while a
command runs.  The first signal raises :class:`Interrupted` (a
:class:`KeyboardInterrupt`) in the main thread; the stack unwinds through the
writers' ``atomic_output`` blocks and the run's
:class:`~mems_stereo.cli._outputs.OutputPlan`, which remove every temporary
file; the command then exits with 128 + the signal's number and one line
that says whether the outputs were written (a signal that arrives while the
outputs are committed is held back until they all are) or none.

A signal is remembered even if some library swallowed the exception: a run
that received one never commits its outputs and never exits 0.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

from mems_stereo.util.atomic import defer_signal, deferring, signals_blocked

#: the signals handled, by name
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))

_state: dict = {"depth": 0, "received": None, "old": {}, "rc": None, "kept": []}


class Interrupted(KeyboardInterrupt):
    """Raised by the handler; ``signum`` is the signal's number."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def _handler(signum, frame):  # noqa: ARG001 - signal handler signature
    if _state["received"] is None:
        _state["received"] = signum
    if deferring():  # a commit or clean-up is running: it raises the signal again at its end
        defer_signal(signum)
        return
    raise Interrupted(signum)


def received() -> int | None:
    """The first signal received inside the outermost guard (None: none)."""
    return _state["received"]


def nested(own: int = 1) -> bool:
    """True inside a command run by another (``demo``), for a caller that holds
    ``own`` guards itself (main(): 1; run_command() inside main(): 2)."""
    return _state["depth"] > own


def _unraisable(unraisable) -> None:
    """An interrupt raised where Python cannot propagate it (a weakref callback, a
    ``__del__``) is not printed as a traceback: :func:`received` remembers it and
    the run ends as interrupted."""
    if isinstance(unraisable.exc_value, Interrupted):
        return
    _state.get("hook", sys.__unraisablehook__)(unraisable)


def _late_handler(signum, frame):  # noqa: ARG001 - signal handler signature
    """After the program's run: nothing is left to clean up; say so and exit 128 + signal."""
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        print(f"mems-stereo: interrupted by {signal.Signals(signum).name} {late_state()}",
              file=sys.stderr)
        sys.stderr.flush()
    os._exit(128 + signum)


def exit_now(rc: int) -> None:
    """End the program with ``rc`` without the interpreter's shutdown (never returns).

    The interpreter's shutdown takes a noticeable time (module and library
    teardown, long with Open3D loaded) in which it restores
    the default signal actions and drops a signal already received but not
    yet handled: a run that had finished could then exit 0 although it was
    interrupted, or die silently.  Instead the exit functions (``atexit``)
    and the other threads are finished with :func:`_late_handler` in place,
    the signals are blocked, one that is pending is reported (exit 128 +
    signal, with what was kept), and the process ends with ``os._exit``.
    """
    with contextlib.suppress(Exception):
        for t in threading.enumerate():
            if t is not threading.current_thread() and not t.daemon:
                t.join()
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    if threading.current_thread() is threading.main_thread():
        signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
        # a signal another thread took is handled by the interpreter before this line
        # ends; one sent to this thread now waits in the kernel: report it
        pending = sorted(set(signal.sigpending()) & set(SIGNALS))
        if pending and rc <= 128:
            _late_handler(pending[0], None)
    os._exit(rc)


def committed(paths) -> None:
    """Record the outputs a run committed (called with the signals held back)."""
    _state["kept"] = _state["kept"] + [str(p) for p in paths]


def late_state() -> str:
    """What an interrupt outside a command's own guard leaves: the truth, in words."""
    if _state["kept"]:
        return "after every output was written: " + ", ".join(_state["kept"])
    if _state["rc"] is not None:
        return f"after the run had finished (exit code {_state['rc']}); nothing was undone"
    return "before any work; nothing was written"


def finished(rc: int) -> None:
    """Record the program's exit code (shown if a signal arrives while it exits)."""
    _state["rc"] = rc


@contextlib.contextmanager
def signal_guard(final: bool = False) -> Iterator[None]:
    """Handle SIGINT/SIGTERM/SIGHUP inside the block (main thread only; nests).

    ``final``: the block is the program's whole run (the ``mems-stereo``
    executable); after it a signal no longer interrupts anything, and instead
    of the previous handlers one that reports it and exits 128 + signal stays.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _state["depth"] == 0:
        _state.update(received=None, rc=None, kept=[])
        _state["old"] = {s: signal.signal(s, _handler) for s in SIGNALS}
        _state["hook"] = sys.unraisablehook
        sys.unraisablehook = _unraisable
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0:
            with blocked():
                for s, old in _state["old"].items():
                    signal.signal(s, _late_handler if final else old)
                _state["old"] = {}
                if not final:
                    sys.unraisablehook = _state["hook"]


#: hold the signals back inside a block (delivered when it ends)
blocked = signals_blocked


def depth() -> int:
    """How many guards are active (main() and run_command() hold one each)."""
    return _state["depth"]
