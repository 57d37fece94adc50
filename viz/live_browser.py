"""The browser viewer of ``mems-stereo live --view browser``: a page served on the loopback.

:class:`BrowserViewer` runs a small HTTP + WebSocket server (Tornado, in a thread of its
own) that serves a self-contained page (``viz/web/``: HTML, JavaScript and CSS shipped
with the package; nothing fetched from elsewhere) at ``http://HOST:PORT/`` and pushes
each frame to every open page over the WebSocket ``ws://HOST:PORT/frames``.  The page
draws the cloud on a 2D canvas coloured by range (or ``sigma_r``, or ``age``), shows the
frame's index, time, point count and the frames dropped so far, and a point's
attributes on hover.

One WebSocket message per frame (binary, little-endian), :func:`frame_message`:

========  ==========================================================================
bytes     content
========  ==========================================================================
0-3       ``uint32`` L: length of the JSON header
4-(4+L)   the header, UTF-8 JSON: ``format`` ``"mems-stereo/live-frame"``,
          ``version`` 1, ``index``, ``start``, ``end`` (s, the source's clock),
          ``points`` (n), ``dropped`` (frames dropped before this one), ``fields``
then      zero padding to a multiple of 4 bytes, then ``float32`` [len(fields), n]:
          one row per field of :data:`FIELDS`, in that order
========  ==========================================================================

A page that is slower than the frames is sent the newest frame when its previous one has
gone out (the frames in between are not sent to it; the files and bags get every frame).
"""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

import numpy as np

from mems_stereo.errors import OptionError

#: the folder of the page's static files (package data)
WEB = Path(__file__).with_name("web")
#: per-point rows of a frame message: x y z (m, receiver camera frame), range,
#: sigma_r (m), age (frames), dt (s, the point's time minus the frame's start)
FIELDS = ("x", "y", "z", "range", "sigma_r", "age", "dt")
MESSAGE_FORMAT = "mems-stereo/live-frame"


def frame_message(frame, dropped: int = 0) -> bytes:
    """The WebSocket message of one frame (layout in the module doc).

    frame : :class:`~mems_stereo.pipeline.frames.Frame`.  dropped : frames dropped so
    far before it.  Missing attributes are sent as NaN (``age``: 1, ``dt``: NaN).
    """
    c = frame.cloud
    n = len(c)
    rows = np.full((len(FIELDS), n), np.nan, dtype="<f4")
    rows[:3] = np.asarray(c.points, np.float64).T
    for i, name in enumerate(FIELDS[3:6], start=3):
        if name in c.attributes:
            rows[i] = np.asarray(c.attributes[name], np.float64)
        elif name == "age":
            rows[i] = 1
    if "t" in c.attributes:
        rows[6] = np.asarray(c.attributes["t"], np.float64) - frame.start
    head = json.dumps({"format": MESSAGE_FORMAT, "version": 1, "index": int(frame.index),
                       "start": float(frame.start), "end": float(frame.end), "points": n,
                       "dropped": int(dropped), "fields": list(FIELDS)}).encode()
    pad = b"\0" * (-(4 + len(head)) % 4)
    return np.uint32(len(head)).astype("<u4").tobytes() + head + pad + rows.tobytes()


def colormap_table(name: str = "turbo") -> list:
    """256 colours [[r, g, b], ...] (0-255) of the package's colormap, for the page."""
    from mems_stereo.viz.colormap import apply_colormap

    rgb = apply_colormap(np.linspace(0.0, 1.0, 256), name)
    return np.round(np.asarray(rgb)[:, :3] * 255).astype(int).tolist()


def _bind(host: str, port: int):
    from tornado.netutil import bind_sockets

    try:
        return bind_sockets(port, address=host)
    except OSError as e:
        raise OptionError(f"cannot serve the browser viewer on {host}:{port} ({e.strerror})",
                          field="--view-port") from None


class BrowserViewer:
    """Frames shown in a browser page served on ``http://HOST:PORT/`` (the module doc).

    host : the address to listen on (127.0.0.1: this machine only).  port : TCP port, 0
    for a free one (:attr:`port` says which).  ``write(frame)`` sends a frame to the open
    pages; ``close()`` stops the server.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765):
        sockets = _bind(host, port)
        self.port = sockets[0].getsockname()[1]
        self.url = f"http://{host if ':' not in host else f'[{host}]'}:{self.port}/"
        self.frames = 0  # frames written
        self.dropped = 0  # frames dropped before the last one written (index gaps)
        self._next = 0  # the index expected next
        self.clients: set = set()
        self.latest: bytes | None = None
        self._loop = asyncio.new_event_loop()
        self._server = None
        ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(sockets, ready),
                                        name="mems-stereo-viewer", daemon=True)
        self._thread.start()
        ready.wait(10)

    # ---------------------------------------------------------------- server thread
    def _serve(self, sockets, ready) -> None:
        from tornado.httpserver import HTTPServer

        asyncio.set_event_loop(self._loop)
        self._server = HTTPServer(_application(self))
        self._server.add_sockets(sockets)
        self._loop.call_soon(ready.set)
        self._loop.run_forever()
        self._loop.close()

    def _broadcast(self, msg: bytes) -> None:
        self.latest = msg
        for c in list(self.clients):
            c.send_frame(msg)

    def _stop(self) -> None:
        self._server.stop()
        for c in list(self.clients):
            c.close()
        self._loop.call_later(0.05, self._loop.stop)

    # ---------------------------------------------------------------- the sink
    def write(self, frame) -> str:
        """Send ``frame`` to the open pages (and keep it for pages opened later)."""
        self.dropped += max(0, int(frame.index) - self._next)
        self._next = int(frame.index) + 1
        msg = frame_message(frame, self.dropped)
        self._loop.call_soon_threadsafe(self._broadcast, msg)
        self.frames += 1
        return self.url

    def close(self) -> None:
        if self._thread is not None:
            self._loop.call_soon_threadsafe(self._stop)
            self._thread.join(5)
            self._thread = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _application(viewer: BrowserViewer):
    """The Tornado application: the page, its files, the colormap and the frame socket."""
    import tornado.web
    import tornado.websocket

    class Page(tornado.web.RequestHandler):
        def get(self):
            self.set_header("Content-Type", "text/html; charset=utf-8")
            self.set_header("Cache-Control", "no-store")
            self.write((WEB / "live.html").read_bytes())

    class Colormap(tornado.web.RequestHandler):
        def get(self):
            self.write({"turbo": colormap_table("turbo")})

    class Frames(tornado.websocket.WebSocketHandler):
        busy = None  # the write still going out to this page
        pending: bytes | None = None  # the newest frame waiting for it

        def open(self):
            viewer.clients.add(self)
            if viewer.latest is not None:
                self.send_frame(viewer.latest)

        def on_close(self):
            viewer.clients.discard(self)

        def send_frame(self, msg: bytes) -> None:
            if self.busy is not None and not self.busy.done():
                self.pending = msg  # sent when the previous one is out
                return
            try:
                self.busy = self.write_message(msg, binary=True)
            except tornado.websocket.WebSocketClosedError:
                viewer.clients.discard(self)
                return
            self.busy.add_done_callback(self._sent)

        def _sent(self, fut) -> None:
            if not fut.cancelled() and fut.exception() is not None:  # the page went away
                viewer.clients.discard(self)
            msg, self.pending = self.pending, None
            if msg is not None and self in viewer.clients:
                self.send_frame(msg)

    class NoIcon(tornado.web.RequestHandler):
        def get(self):
            self.set_status(204)

    return tornado.web.Application([
        (r"/", Page),
        (r"/favicon\.ico", NoIcon),
        (r"/colormap\.json", Colormap),
        (r"/frames", Frames),
        (r"/(live\.js|live\.css)", tornado.web.StaticFileHandler, {"path": str(WEB)}),
    ], log_function=lambda _handler: None)  # no access log on the terminal
