"""Shot chunks on a ZeroMQ socket: the message layout any acquisition program can send.

The acquisition program binds a ``PUSH`` socket (``tcp://*:5555``) and sends
multipart messages; ``mems-stereo live tcp://HOST:5555`` connects a ``PULL`` socket
(``tcp://*:PORT`` binds instead, for a sender that connects).  Every message starts
with a JSON header (UTF-8), declared as the ``live-message`` schema in
docs/formats.md; the parts after it are raw little-endian arrays (docs/live.md):

| ``type`` | parts after the header |
| --- | --- |
| ``"system"`` (first message) | the system description JSON (``mems-stereo/system``) |
| ``"shots"`` | time ``<f8`` [k], bins ``<u2`` [k·H·W] (shot, row, column), |
| | zero crossings ``<f8`` [z], rising ``u1`` [z] |
| ``"end"`` | none: the stream is finished |

with ``n_shots`` = k and ``n_zero_crossings`` = z in the header (either may be 0).
A ZeroMQ multipart message arrives whole or not at all; a message whose parts do
not match its header is refused (:class:`~mems_stereo.errors.FormatError`), never
read as data.  :func:`send_system`, :func:`send_shots` and :func:`send_end` are the
sender in Python.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import numpy as np

from mems_stereo.errors import FormatError, OptionError
from mems_stereo.io.live_sources import LiveSource, ShotRelease, check_codes
from mems_stereo.io.recording import Recording
from mems_stereo.model.system import System, system_from_json, system_to_json
from mems_stereo.util.jsonfile import FieldChecker, check_schema
from mems_stereo.util.schemas import LIVE_MESSAGE_FIELDS

LIVE_FORMAT = "mems-stereo/live"
#: milliseconds a receive waits before the source looks at its stop flag and idle time
POLL_MS = 50
_PARTS = {"system": 1, "shots": 4, "end": 0}


def _zmq():
    try:
        import zmq
    except ImportError:  # pragma: no cover - a declared dependency
        raise OptionError("a ZeroMQ source needs the 'pyzmq' package (pip install pyzmq)",
                          field="SOURCE") from None
    return zmq


def _header(kind: str, **extra) -> bytes:
    return json.dumps({"format": LIVE_FORMAT, "version": 1, "type": kind, **extra}).encode()


def send_system(sock, system: System) -> None:
    """Send the ``system`` message (first, once)."""
    sock.send_multipart([_header("system"), system_to_json(system).encode()])


def send_shots(sock, shot_time, bins, zero_crossings=(), rising=()) -> None:
    """Send a ``shots`` message: (k,) float64 s, (k, H, W) uint16, (z,) float64 s, (z,) 0/1."""
    t = np.ascontiguousarray(shot_time, "<f8").ravel()
    b = np.ascontiguousarray(bins, "<u2")
    z = np.ascontiguousarray(zero_crossings, "<f8").ravel()
    r = np.ascontiguousarray(rising, "u1").ravel()
    sock.send_multipart([_header("shots", n_shots=int(t.size), n_zero_crossings=int(z.size)),
                         t.tobytes(), b.tobytes(), z.tobytes(), r.tobytes()])


def send_end(sock) -> None:
    """Send the ``end`` message (the stream is finished)."""
    sock.send_multipart([_header("end")])


class ZmqSource(LiveSource):
    """Shot chunks from a ZeroMQ ``PULL`` socket (see the module doc).

    Waits up to ``idle_timeout`` s (None: without limit) for the ``system`` message,
    then yields the shots as their zero crossings come; ends at ``end``, after
    ``idle_timeout`` s without a message, or at :meth:`stop`.
    """

    def __init__(self, address: str, idle_timeout: float | None = 10.0, context=None):
        zmq = _zmq()
        self.address = address
        self.idle_timeout = idle_timeout
        self._ctx = context or zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.PULL)
        self._sock.setsockopt(zmq.LINGER, 0)
        try:
            if "://*" in address or "://0.0.0.0" in address:
                self._sock.bind(address)
            else:
                self._sock.connect(address)
        except zmq.ZMQError as e:
            self._sock.close()
            raise OptionError(f"cannot open {address} ({e})", field="SOURCE") from None
        self.count = 0
        super().__init__(None, address)
        kind, parts = self._receive(first=True)
        if kind != "system":
            self._sock.close()
            raise FormatError(f"expected a 'system' message first, found {kind!r}", address,
                              "type")
        self.system = system_from_json(parts[0].decode("utf-8", "replace"),
                                       source=f"{address} system message")

    def _receive(self, first: bool = False):
        """``(type, parts)`` of the next message; ``("idle", [])`` after the idle time,
        ``("stopped", [])`` at :meth:`stop`."""
        t0 = time.monotonic()
        while not self.stopped:
            if self._sock.poll(POLL_MS):
                return self._decode(self._sock.recv_multipart(copy=True))
            if self.idle_timeout is not None and time.monotonic() - t0 > self.idle_timeout:
                if first:
                    self._sock.close()
                    raise FormatError(f"no message in {self.idle_timeout:g} s", self.address)
                return "idle", []
        return "stopped", []

    def _decode(self, msg: list) -> tuple[str, list]:
        self.count += 1
        where = f"{self.address} message {self.count}"
        try:
            head = json.loads(msg[0].decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as e:
            raise FormatError(f"expected a JSON header, found undecodable bytes ({e})"[:160],
                              where) from None
        check_schema(head, LIVE_MESSAGE_FIELDS, FieldChecker(where))
        kind = head["type"]
        if kind not in _PARTS:
            raise FormatError(f"expected 'system', 'shots' or 'end', found {kind!r}", where,
                              "type")
        if len(msg) - 1 != _PARTS[kind]:
            raise FormatError(f"expected {_PARTS[kind]} parts after the header, found "
                              f"{len(msg) - 1}", where, "type")
        if kind == "shots":
            if self.system is None:
                raise FormatError("expected a 'system' message first, found 'shots'", where,
                                  "type")
            return kind, self._arrays(head, msg[1:], where)
        return kind, msg[1:]

    def _arrays(self, head: dict, parts: list, where: str) -> list:
        k, z = int(head.get("n_shots", 0)), int(head.get("n_zero_crossings", 0))
        h, w = self.system.receiver.height, self.system.receiver.width
        want = [("time", "<f8", k), ("bins", "<u2", k * h * w),
                ("zero_crossings", "<f8", z), ("rising", "u1", z)]
        out = []
        for (name, dt, n), p in zip(want, parts):
            if len(p) != n * np.dtype(dt).itemsize:
                raise FormatError(f"expected {n} values ({n * np.dtype(dt).itemsize} bytes), "
                                  f"found {len(p)} bytes", where, name)
            out.append(np.frombuffer(p, dt).astype(np.dtype(dt).newbyteorder("=")))
        out[1] = out[1].reshape(k, h, w)
        check_codes(out[1], self.system, where, "the message's bins")
        return out

    def chunks(self) -> Iterator[Recording]:
        rel = ShotRelease(self.system, self.source)
        try:
            while True:
                kind, parts = self._receive()
                if kind == "shots":
                    t, b, zc, ri = parts
                    rel.add(zc=zc, rising=ri)
                    rel.add(times=t, bins=b)
                    got = rel.take()
                elif kind in ("end", "idle", "stopped"):
                    got = rel.take(final=kind != "stopped")
                    self.ended = {"end": "finished"}.get(kind, kind)
                else:
                    raise FormatError("expected one 'system' message, found another",
                                      self.source, "type")
                if got is not None:
                    yield self.chunk(*got)
                if self.ended is not None:
                    return
        finally:
            self._sock.close()
