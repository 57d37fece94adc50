"""The browser viewer of ``mems-stereo live --view browser`` in a real headless browser.

Debian's ``chromium`` driven through Debian's ``chromium-driver`` by Selenium (both
installed by ``scripts/setup.sh``; Selenium is in the ``dev`` extra).  The page is the
package's own (``viz/web``), served by :class:`~mems_stereo.viz.live_browser.BrowserViewer`
on the loopback; the tests wait until the page reports the frame it received and look at
what it drew.  Skipped only where chromium or its driver is absent.
"""

from __future__ import annotations

import io
import shutil
import threading
import time

import numpy as np
import pytest

from mems_stereo import data
from mems_stereo.pipeline.cloud import PointCloud
from mems_stereo.pipeline.frames import Frame
from mems_stereo.pipeline.pass1 import Counts

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None or DRIVER is None,
    reason="Debian's chromium and chromium-driver are not installed (scripts/setup.sh "
           "installs them)")
BACKGROUND = (17, 17, 17)  # the page's background (viz/web/live.css)


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=900,640"):
        opts.add_argument(a)
    drv = webdriver.Chrome(options=opts, service=Service(DRIVER))
    yield drv
    drv.quit()


def _wait_for(drv, done, timeout: float = 8.0) -> dict:
    """The page's ``window.msViewer`` once ``done(state)`` holds (fails after timeout)."""
    t_end = time.monotonic() + timeout
    st = None
    while time.monotonic() < t_end:
        st = drv.execute_script("return window.msViewer || null")
        if st and (st.get("error") or done(st)):
            break
        time.sleep(0.05)
    assert st and not st.get("error") and done(st), st
    return st


def _fan_frame(seed: int = 7, n: int = 3000) -> Frame:
    """A frame of points on a fan whose range grows from 2 m (left) to 5 m (right)."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.3, 0.3, n)
    r = 2 + 3 * (az + 0.6) / 1.2
    d = np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], axis=1)
    attrs = {"range": r, "sigma_r": 0.005 * r, "age": rng.integers(1, 9, n).astype(np.int32),
             "t": rng.uniform(0.3, 0.4, n)}
    return Frame(index=3, start=0.3, end=0.4, cloud=PointCloud(d * r[:, None], attrs),
                 counts=Counts(shots=100, shots_unknown_angle=0, raw=n, signal=n, noise=0))


def _canvas_pixels(drv) -> np.ndarray:
    from PIL import Image

    png = drv.find_element("id", "cloud").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_page_draws_a_frame_coloured_by_range(browser, tmp_path):
    from mems_stereo.viz.live_browser import BrowserViewer, colormap_table

    frame = _fan_frame()
    with BrowserViewer(port=0) as v:
        v.write(frame)  # before the page opens: a page gets the newest frame on connecting
        browser.get(v.url)
        st = _wait_for(browser, lambda s: s["frames"] >= 1)
        assert (st["index"], st["points"], st["dropped"]) == (3, 3000, 3)  # frames 0-2 missing
        assert abs(st["start"] - 0.3) < 1e-12 and abs(st["end"] - 0.4) < 1e-12
        assert "frame 3" in browser.find_element("id", "status").text
        img = _canvas_pixels(browser)
        (tmp_path / "page.png").write_bytes(browser.get_screenshot_as_png())
        drawn = (img != BACKGROUND).any(axis=2)
        assert st["drawn"] > 0.9 * 3000 and drawn.sum() > 3000  # 3x3 px points, few hidden
        # range grows to the right: the turbo map's blue end left, its red end right
        cols = np.nonzero(drawn.any(axis=0))[0]
        third = (cols[-1] - cols[0]) // 3
        left, right = img[:, cols[0]:cols[0] + third], img[:, cols[-1] - third:cols[-1] + 1]
        lm, rm = drawn[:, cols[0]:cols[0] + third], drawn[:, cols[-1] - third:cols[-1] + 1]
        assert left[lm][:, 2].mean() > left[lm][:, 0].mean() + 40  # blue over red
        assert right[rm][:, 0].mean() > right[rm][:, 2].mean() + 40  # red over blue
        lut = np.array(colormap_table())
        some = img[drawn][:: max(1, drawn.sum() // 200)]
        dist = np.abs(some[:, None, :] - lut[None]).sum(axis=2).min(axis=1)
        assert np.median(dist) <= 6  # the package's colormap (antialiasing aside)
        # sigma on hover: the tooltip of the drawn pixel nearest the canvas centre
        from selenium.webdriver import ActionChains

        ys, xs = np.nonzero(drawn)
        k = np.argmin((ys - img.shape[0] / 2) ** 2 + (xs - img.shape[1] / 2) ** 2)
        canvas = browser.find_element("id", "cloud")
        ActionChains(browser).move_to_element_with_offset(
            canvas, int(xs[k] - img.shape[1] // 2), int(ys[k] - img.shape[0] // 2)).perform()
        tip = browser.find_element("id", "tip")
        assert tip.is_displayed() and "σ" in tip.text and "range" in tip.text, tip.text
        rng_shown = float(tip.text.split("range ")[1].split(" m")[0])
        sig_shown = float(tip.text.split("σ ")[1].split(" mm")[0])
        assert 2.0 <= rng_shown <= 5.0 and abs(sig_shown - 5.0 * rng_shown) < 0.2


def test_frames_pushed_to_an_open_page(browser):
    """An open page gets each frame as it is written: index, time window, point count,
    and the frames dropped so far (the gaps in the indices written)."""
    from mems_stereo.viz.live_browser import BrowserViewer

    with BrowserViewer(port=0) as v:
        browser.get(v.url)
        st = _wait_for(browser, lambda s: s["connected"])
        assert st["frames"] == 0 and st["index"] is None
        for index, n, dropped in ((0, 0, 0), (1, 800, 0), (4, 300, 2)):  # 0: no point yet
            f = _fan_frame(seed=index, n=n)
            v.write(Frame(index, 0.1 * index, 0.1 * index + 0.1, f.cloud, f.counts))
            st = _wait_for(browser, lambda s, i=index: s["index"] == i)
            assert (st["points"], st["dropped"]) == (n, dropped)
            assert abs(st["start"] - 0.1 * index) < 1e-12 and st["drawn"] >= 0.9 * n
        assert v.frames == 3 and v.dropped == 2


@pytest.mark.slow
def test_live_command_serves_the_page_until_ctrl_c(browser, tmp_path):
    """``mems-stereo live --replay … --view browser --view-keep``: the page shows the last
    frame the command wrote (its point count read back from the frame's file), the server
    stays after the stream ends, and Ctrl-C ends the command cleanly."""
    import os
    import queue
    import signal
    import subprocess
    import sys

    from mems_stereo.viz.export import read_cloud

    out = tmp_path / "frames"
    cmd = [sys.executable, "-c", "import sys; from mems_stereo.cli import main; sys.exit(main())",
           "live", "--replay", str(data.path("room.h5")), "--rate", "max", "--frame-rate", "50",
           "--view", "browser", "--view-port", "0", "--view-keep", "-o", f"{out}/"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln) for ln in p.stdout], daemon=True)
    reader.start()
    try:
        got = [lines.get(timeout=30)]
        assert got[0].startswith("browser viewer: http://127.0.0.1:"), got
        url = got[0].split(": ", 1)[1].strip()
        while "stays open" not in got[-1]:
            got.append(lines.get(timeout=30))
        assert "2 frames written, 0 dropped" in "".join(got), got
        browser.get(url)
        st = _wait_for(browser, lambda s: s["index"] == 1)
        assert st["points"] == len(read_cloud(out / "room_000001.ply")) and st["dropped"] == 0
        p.send_signal(signal.SIGINT)
        p.wait(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
    err = p.stderr.read()
    assert p.returncode == 0 and err == "", err
