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

import contextlib
import signal
import threading
from collections.abc import Iterator

from mems_stereo.util.atomic import signals_blocked

#: the signals handled, by name
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))

_state: dict = {"depth": 0, "received": None, "old": {}}


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
    raise Interrupted(signum)


def received() -> int | None:
    """The first signal received inside the outermost guard (None: none)."""
    return _state["received"]


def nested() -> bool:
    """True inside a guard that is itself inside another (a command run by ``demo``)."""
    return _state["depth"] > 1


@contextlib.contextmanager
def signal_guard() -> Iterator[None]:
    """Handle SIGINT/SIGTERM/SIGHUP inside the block (main thread only; nests)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _state["depth"] == 0:
        _state["received"] = None
        _state["old"] = {s: signal.signal(s, _handler) for s in SIGNALS}
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0:
            with blocked():
                for s, old in _state["old"].items():
                    signal.signal(s, old)
                _state["old"] = {}


#: hold the signals back inside a block (delivered when it ends)
blocked = signals_blocked
