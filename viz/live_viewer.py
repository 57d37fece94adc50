"""Live viewers of frames (``mems-stereo live --view KIND``): an Open3D window, a page in
a browser, or the Foxglove app.

:func:`open_viewer` gives a sink with ``write(frame)`` and ``close()``, like the frame
writers of :mod:`mems_stereo.viz.export_frames`:

- :class:`Open3DViewer` (``open3d``) where there is a display: one window whose cloud is
  replaced by each frame's, coloured by range (turbo, :mod:`mems_stereo.viz.colormap`).
- :class:`~mems_stereo.viz.live_browser.BrowserViewer` (``browser``, the choice of
  ``auto`` without a display): a self-contained page served on ``http://127.0.0.1:PORT/``
  (nothing fetched from elsewhere), frames pushed to it over a WebSocket.
- :class:`FoxgloveViewer` (``foxglove``): a Foxglove WebSocket server (the ``foxglove-sdk``
  package, optional: ``pip install mems-stereo[live-viewer]``) on
  ``ws://HOST:PORT`` publishing each frame as a ``foxglove.PointCloud`` on
  ``/mems_stereo/points`` (frame ``mems_stereo_receiver_optical_frame``, stamped with the
  frame's start) with the fields ``x y z`` (float32, m), ``range``, ``sigma_r`` (float32,
  m), ``t`` (float64, s) and ``age`` (uint32): open it in Foxglove ("Open connection")
  and colour by ``range`` or ``sigma_r``.
"""

from __future__ import annotations

import numpy as np

from mems_stereo.errors import OptionError

TOPIC = "/mems_stereo/points"
FRAME_ID = "mems_stereo_receiver_optical_frame"
#: the fields published per point: name, numpy dtype, foxglove numeric type name
FIELDS = (("x", "<f4", "Float32"), ("y", "<f4", "Float32"), ("z", "<f4", "Float32"),
          ("range", "<f4", "Float32"), ("sigma_r", "<f4", "Float32"), ("t", "<f8", "Float64"),
          ("age", "<u4", "Uint32"))


def packed_points(cloud) -> np.ndarray:
    """(N,) structured array of :data:`FIELDS` (missing attributes: NaN, age 1)."""
    n = len(cloud)
    rec = np.zeros(n, dtype=[(name, dt) for name, dt, _ in FIELDS])
    for i, k in enumerate("xyz"):
        rec[k] = cloud.points[:, i]
    for name, _dt, _ in FIELDS[3:]:
        if name in cloud.attributes:
            rec[name] = np.asarray(cloud.attributes[name])
        else:
            rec[name] = 1 if name == "age" else np.nan
    return rec


class FoxgloveViewer:
    """Frames published on a Foxglove WebSocket server (see the module doc)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765):
        try:
            import foxglove
            from foxglove.channels import PointCloudChannel
        except ImportError:
            raise OptionError("the browser viewer needs the 'foxglove-sdk' package (pip install "
                              "'mems-stereo[live-viewer]')", field="--view") from None
        self._fx = foxglove
        self.server = foxglove.start_server(name="mems-stereo live", host=host, port=port)
        self.port = self.server.port
        self.url = f"ws://{host}:{self.port}"
        self.channel = PointCloudChannel(TOPIC)
        self.frames = 0

    def write(self, frame) -> str:
        from foxglove import messages as m

        rec = packed_points(frame.cloud)
        off = [rec.dtype.fields[name][1] for name, _, _ in FIELDS]
        fields = [m.PackedElementField(name=name, offset=int(o),
                                       type=getattr(m.PackedElementFieldNumericType, ft))
                  for (name, _dt, ft), o in zip(FIELDS, off)]
        ns = max(0, int(round(frame.start * 1e9)))
        msg = m.PointCloud(timestamp=m.Timestamp(sec=ns // 10**9, nsec=ns % 10**9),
                           frame_id=FRAME_ID, point_stride=rec.dtype.itemsize, fields=fields,
                           data=rec.tobytes())
        self.channel.log(msg, log_time=ns)
        self.frames += 1
        return self.url

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class Open3DViewer:
    """One Open3D window showing the latest frame, coloured by range."""

    def __init__(self, title: str = "mems-stereo live", visible: bool = True):
        import open3d as o3d

        self._o3d = o3d
        self.vis = o3d.visualization.Visualizer()
        if not self.vis.create_window(window_name=title, width=1024, height=768,
                                      visible=visible):
            raise OptionError("cannot open an Open3D window (no OpenGL)", field="--view")
        self.pcd = o3d.geometry.PointCloud()
        self.frames = 0

    def write(self, frame):
        from mems_stereo.viz.colormap import cloud_colors

        c = frame.cloud
        self.pcd.points = self._o3d.utility.Vector3dVector(np.asarray(c.points, np.float64))
        if len(c) and "range" in c.attributes:
            self.pcd.colors = self._o3d.utility.Vector3dVector(cloud_colors(c, "range"))
        if self.frames == 0:
            self.vis.add_geometry(self.pcd)  # the view is fitted to the first frame
        else:
            self.vis.update_geometry(self.pcd)
        self.vis.poll_events()
        self.vis.update_renderer()
        self.frames += 1

    def close(self) -> None:
        if self.vis is not None:
            self.vis.destroy_window()
            self.vis = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


#: the viewers ``open_viewer`` knows
VIEWERS = ("auto", "open3d", "browser", "foxglove")


def open_viewer(kind: str = "auto", port: int = 8765, host: str = "127.0.0.1"):
    """The viewer sink: ``"open3d"``, ``"browser"`` (the page of
    :mod:`~mems_stereo.viz.live_browser`), ``"foxglove"`` (Foxglove WebSocket) or
    ``"auto"`` (Open3D where there is a display, else the browser page).  port, host:
    where the browser page or the Foxglove server listens (port 0: a free one)."""
    if kind not in VIEWERS:
        raise OptionError(f"expected one of {', '.join(VIEWERS)}, found {kind!r}", field="--view")
    if kind == "auto":
        from mems_stereo.viz.view import has_display

        kind = "open3d" if has_display() else "browser"
    if kind == "open3d":
        return Open3DViewer()
    if kind == "foxglove":
        return FoxgloveViewer(host=host, port=port)
    from mems_stereo.viz.live_browser import BrowserViewer

    return BrowserViewer(host=host, port=port)
