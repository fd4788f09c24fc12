"""The live view in a real browser: headless Chromium (Debian's package, driven by Playwright)
opens the view of a running ``fimnav launch --view`` (real processes on 127.0.0.1) and a
screenshot shows the drones, in the view's colour for a drone that is alive, while the launch
still flies. Ctrl-C then ends the launch; the recording is complete and rerun's server is gone.

Run with ``FIMNAV_CHROMIUM=/usr/bin/chromium`` and Playwright installed (``pip install -e
'.[browser]'``, not in the test install); add ``FIMNAV_LIVE_VIEW_PNG=docs/figures/live-view.png``
to keep the screenshot (the one in docs/in-the-field.md is made that way).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from missions.launch.liveview import STATE_COLOURS
from tests.support.launch import PAPER, Launch, processes_mentioning
from tests.support.wait import wait_for

#: The browser, named like the SITL binaries: the test takes about 40 s of the default run's
#: 5 minutes on two cores, so it runs when asked (FIMNAV_CHROMIUM=/usr/bin/chromium).
CHROMIUM = shutil.which(os.environ.get("FIMNAV_CHROMIUM", "")) if os.environ.get("FIMNAV_CHROMIUM") else None
#: Playwright, a third-party driver in its own extra (fimnav[browser]), not in the test install.
PLAYWRIGHT = importlib.util.find_spec("playwright") is not None
pytestmark = [
    pytest.mark.integration,
    pytest.mark.browser,
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="set FIMNAV_CHROMIUM to a Chromium binary (Debian's chromium: /usr/bin/chromium) and pip install -e '.[browser]' (Playwright) to run it",
    ),
    pytest.mark.skipif(not PLAYWRIGHT, reason="needs Playwright: pip install -e '.[browser]' (fimnav[browser], not in the test install)"),
]

#: Pixels of the alive-drone colour a screenshot must hold to show the drones (each drone is a
#: sphere of a few pixels across and a label; ten drones give several hundred).
MIN_DRONE_PIXELS = 60


def drone_pixels(png: bytes) -> int:
    """Pixels within 40 (RGB distance) of the alive-drone colour."""
    import io

    from matplotlib.image import imread

    img = imread(io.BytesIO(png), format="png")[..., :3] * 255.0
    return int((np.linalg.norm(img - np.array(STATE_COLOURS["alive"]), axis=-1) < 40.0).sum())


def test_headless_chromium_shows_the_drones_during_a_launch(tmp_path: Path, launches: list[Launch]) -> None:
    from playwright.sync_api import sync_playwright

    out = tmp_path / "run"
    run = Launch(PAPER / "heterogeneous.yaml", out, "--steps", "1000", "--view")
    launches.append(run)
    view_json = out / "logs" / "view.json"
    wait_for(lambda: view_json.exists() or run.proc.poll() is not None, 120.0, "the launch to start its view")
    assert run.proc.poll() is None, run.wait()[2][-2000:]
    url = json.loads(view_json.read_text())["url"]
    assert url.startswith("http://127.0.0.1:")
    web_port = url.split(":")[2].split("/")[0]
    shot = tmp_path / "live-view.png"
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 800})
            page.goto(url)
            deadline = time.monotonic() + 90.0
            while True:
                png = page.screenshot()
                if drone_pixels(png) >= MIN_DRONE_PIXELS:
                    break
                if time.monotonic() > deadline:
                    shot.write_bytes(png)
                    pytest.fail(f"no drones in the view after 90 s ({drone_pixels(png)} drone pixels; screenshot {shot})")
                page.wait_for_timeout(1000)  # the polling interval of the deadline wait above
            flying = run.proc.poll() is None
        finally:
            browser.close()
    shot.write_bytes(png)
    if os.environ.get("FIMNAV_LIVE_VIEW_PNG"):
        Path(os.environ["FIMNAV_LIVE_VIEW_PNG"]).write_bytes(png)
    assert flying, "the launch ended before the browser showed the drones"
    # Ctrl-C ends the launch: every process, rerun's server included, is gone; the recording stays.
    os.killpg(run.proc.pid, signal.SIGINT)
    code, _, stderr = run.wait(60.0)
    assert code == 130, stderr[-2000:]
    wait_for(lambda: not processes_mentioning(f"--web-viewer-port {web_port}"), 15.0, "rerun's server to exit")
    assert (out / "view.rrd").stat().st_size > 10_000
