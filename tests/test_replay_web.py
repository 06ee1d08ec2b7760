"""``msdgrasp replay --web`` in a real headless browser: the page loads, the viewer starts, and the
recording's own data is drawn (the three jaw colours of the recorder's 3D jaws and force plots).

Needs Chromium (Debian: ``apt-get install chromium``) and Playwright (``pip install -e ".[browser-test]"``;
Playwright drives the system Chromium, it downloads no browser). Without them the test is skipped and
says why: CI's fresh clone installs neither. Chromium runs with the software rasteriser (no GPU).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from msdgrasp.cli.replay import web_viewer_url
from msdgrasp.envs.grasp_lift import GraspLiftEnv
from msdgrasp.envs.recording import JAW_COLORS, RerunRecorder

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
try:
    from playwright.sync_api import sync_playwright
except ImportError:  # an optional test tool, not a dependency of the package
    sync_playwright = None

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no Chromium here (apt-get install chromium)"),
    pytest.mark.skipif(sync_playwright is None, reason="Playwright not installed (pip install -e '.[browser-test]')"),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_http(url: str, timeout_s: float) -> int:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.status
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.3)


def _colour_pixels(png: bytes) -> list[int]:
    """Pixels within a small distance of each jaw colour of the recorder."""
    import imageio.v3 as iio

    img = iio.imread(png)[:, :, :3].astype(int)
    return [int((np.abs(img - c[:3].astype(int)).sum(axis=-1) < 60).sum()) for c in JAW_COLORS]


def test_replay_web_serves_a_viewer_that_draws_the_recording(tmp_path):
    env = GraspLiftEnv()
    path = tmp_path / "episode.rrd"
    rec = RerunRecorder(env, path)
    rec.reset(seed=0, options={"mu": 0.8})
    for _ in range(15):
        rec.step(np.array([0.3, -1.0], dtype=np.float32))
    rec.finish()

    port, grpc_port = _free_port(), _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "msdgrasp.cli.main", "replay", "--web", "--port", str(port),
                             "--grpc-port", str(grpc_port), str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)  # its own process group: rerun is replay's child
    try:
        url = web_viewer_url(port, grpc_port)
        assert _wait_http(f"http://127.0.0.1:{port}/", 30.0) == 200
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--disable-quic"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            assert "Rerun" in page.title()
            # the wasm viewer compiles, connects to the gRPC server and draws the recording's blueprint
            before = _colour_pixels(page.screenshot())
            counts = before
            end = time.monotonic() + 120.0
            while min(counts) < 40 and time.monotonic() < end:
                page.wait_for_timeout(2000)
                counts = _colour_pixels(page.screenshot())
            browser.close()
        assert min(before) < 40, "the jaw colours must not be on the page before the viewer has drawn"
        assert min(counts) >= 40, f"jaw colours drawn (pixels per jaw colour): {counts}"
        panics = [e for e in errors if "panic" in e.lower() or "RuntimeError" in e]
        assert panics == []
    finally:
        # stop replay AND the rerun server it started (which holds the output pipe open)
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, _ = proc.communicate(timeout=10)
    assert "open http://127.0.0.1" in out  # replay says where to point the browser
