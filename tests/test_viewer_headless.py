"""The service's review recording as a user sees it: rerun's own web viewer, headless Chromium.

A recording made by :class:`RrdLogger` is opened in the web viewer the installed rerun-sdk
serves (``rerun --serve-web URL``), rendered by the system's Chromium (software rasteriser)
driven by Playwright, and the screenshot is judged: the recording's maps are drawn, and each
histogram is a row of separate bars of different heights on one baseline, not one flat block
(issue 24: bars logged without ``widths`` were each drawn 1 unit wide and merged).

The viewer draws everything into one canvas (no text in the DOM or the accessibility tree), so
the checks read pixels (a recording logged without ``widths`` was seen to fail them: each
histogram one block, 1 bar). The screenshot is kept in the test's tmp dir as ``viewer.png``.
Skips with the reason when Chromium, Playwright or the viewer cannot run.
"""

from __future__ import annotations

import functools
import http.server
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("rerun")
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")


from evcal.calibration import Calibration  # noqa: E402
from evcal.events import make_events  # noqa: E402
from evcal.service.rrdlog import RrdLogger  # noqa: E402
from evcal.testing import free_port  # noqa: E402

pytestmark = pytest.mark.timeout(240)

SHAPE = (48, 64)
VIEWPORT = {"width": 1600, "height": 1000}
LOAD_TIMEOUT_S = 150.0  # the wasm viewer alone takes 10-50 s to start on a software rasteriser
# the machine's network is closed: without these Chromium keeps dialling Google's hosts
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]


@pytest.fixture
def chromium() -> str:
    """The system's Chromium (Playwright drives it; it downloads no browser of its own)."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")


def _rerun_cli() -> str:
    local = Path(sys.executable).parent / "rerun"  # the venv's, whether or not it is on PATH
    path = str(local) if local.exists() else shutil.which("rerun")
    if not path:
        pytest.skip("the rerun command of rerun-sdk is not installed")
    return path


def _make_recording(path: Path) -> None:
    """A service recording of one camera whose c and b spread as real maps do (seeded)."""
    rng = np.random.default_rng(24)
    cal = Calibration.uniform(SHAPE, 0.2, 0.0, log_offset=30.0).replace(
        contrast=rng.normal(0.2, 0.03, SHAPE).astype(np.float32),
        bias=rng.normal(0.0, 0.01, SHAPE).astype(np.float32))
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0, recon_period_s=0.0,
                    recon_frames=1)
    status = {"latency_ms": {"last": 5.0}, "event_rate_hz": 1e5, "errors_total": 0}
    for k in range(5):
        t_us = k * 40_000
        log.frame("cam0", t_us + 1, rng.integers(0, 255, SHAPE).astype(np.uint8))
        n = 400
        log.events("cam0", make_events(np.sort(rng.integers(t_us + 2, t_us + 39_000, n)),
                                       rng.integers(0, SHAPE[1], n), rng.integers(0, SHAPE[0], n),
                                       rng.choice([-1, 1], n)))
        log.updated("cam0", cal, t_us + 39_500, status)
    log.close()


class _CorsHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the folder to the viewer's page, which is on another port (another origin)."""

    served: list[str]

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002
        self.served.append(self.path)


@pytest.fixture
def served_recording(tmp_path: Path) -> Iterator[tuple[str, list[str]]]:
    """The recording over HTTP on 127.0.0.1: its URL and the paths requested so far."""
    _make_recording(tmp_path / "review.rrd")
    served: list[str] = []
    handler = type("Handler", (_CorsHandler,), {"served": served})
    server = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(handler, directory=str(tmp_path)))
    thread = threading.Thread(target=server.serve_forever, name="rrd-http", daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/review.rrd", served
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


@pytest.fixture
def viewer_url(served_recording: tuple[str, list[str]]) -> Iterator[str]:
    """rerun's web viewer (only the page: an http URL needs no gRPC server) opening the file."""
    rrd_url, _ = served_recording
    port = free_port()
    # the rerun command is a Python wrapper around the viewer binary: a group of its own, so
    # that stopping it stops the binary too
    proc = subprocess.Popen([_rerun_cli(), "--serve-web", "--bind", "127.0.0.1",
                             "--web-viewer-port", str(port), rrd_url],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    page = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            if proc.poll() is not None:
                pytest.skip(f"rerun --serve-web exited with {proc.returncode}: "
                            f"{proc.stderr.read()[-500:] if proc.stderr else ''}")
            try:
                with urllib.request.urlopen(page, timeout=2) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, OSError):
                pass
            if time.monotonic() > deadline:
                pytest.skip("rerun's web viewer did not answer on its port within 30 s")
            time.sleep(0.2)
        yield f"{page}/?url={urllib.parse.quote(rrd_url, safe='')}"
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(10)
                break
            except subprocess.TimeoutExpired:
                continue
        if proc.stderr:
            proc.stderr.close()


@dataclass(frozen=True)
class BarChart:
    """One colour's bars in a screenshot: ``box`` is (top, baseline, left, right) in pixels,
    ``bars`` the runs of columns holding the colour (bars are separated by their outlines or
    by empty bins), ``heights`` how many different column heights, ``spread`` their std/mean."""

    colour: tuple[int, int, int]
    pixels: int
    box: tuple[int, int, int, int]
    bars: int
    heights: int
    spread: float


def histograms(rgb: np.ndarray, *, min_pixels: int = 400) -> list[BarChart]:
    """The bar charts in a screenshot ``[H, W, 3]``: every saturated colour of at least
    ``min_pixels`` pixels whose pixels stand on one baseline (bars grow up from the axis).
    The bars of a chart drawn without ``widths`` merge into one block: ``bars`` is 1."""
    img = rgb.astype(np.int16)
    saturated = (img.max(2) - img.min(2)) > 40  # the viewer's chrome is grey
    colours, counts = np.unique(img[saturated].reshape(-1, 3), axis=0, return_counts=True)
    found: list[BarChart] = []
    for i in np.argsort(-counts)[:8]:
        if counts[i] < min_pixels:
            break
        mask = np.abs(img - colours[i]).max(2) <= 6  # anti-aliased edges are near the colour
        ys, xs = np.nonzero(mask)
        x0, x1 = int(xs.min()), int(xs.max())
        cols = mask[:, x0:x1 + 1]
        filled = cols.any(0)
        bottom = np.where(filled, cols.shape[0] - 1 - np.argmax(cols[::-1], 0), -1)
        baseline = int(np.bincount(bottom[filled]).argmax())
        on_base = filled & (np.abs(bottom - baseline) <= 1)
        if on_base.sum() < 0.8 * filled.sum():
            continue  # not standing on one axis: a map, a selection, a line
        heights = cols.sum(0)[on_base]
        runs = int(on_base[0]) + int(np.sum(on_base[1:] & ~on_base[:-1]))
        r, g, b = (int(c) for c in colours[i])
        found.append(BarChart(colour=(r, g, b), pixels=int(counts[i]),
                              box=(int(ys.min()), baseline, x0, x1), bars=runs,
                              heights=len(np.unique(heights)),
                              spread=float(heights.std() / max(heights.mean(), 1.0))))
    return found


def _judge(rgb: np.ndarray) -> list[str]:
    """What is wrong with the screenshot (nothing: an empty list)."""
    problems = []
    saturated = rgb[(rgb.max(2).astype(np.int16) - rgb.min(2)) > 40]
    # the viridis and cyan-to-yellow maps bring about 2000 colours; the welcome page or the
    # loading page about 400 (anti-aliased coloured text and icons)
    n_colours = len(np.unique(saturated.reshape(-1, 3), axis=0))
    if n_colours < 1000:
        problems.append(f"{n_colours} saturated colours: the maps are not drawn")
    hists = histograms(rgb)
    readable = [h for h in hists if h.bars >= 15 and h.heights >= 8 and h.spread > 0.3]
    if len(readable) < 2:
        problems.append(f"want 2 histograms (c and b) of >= 15 bars of varied heights, "
                        f"found {hists}")
    return problems


def test_review_recording_reads_in_the_web_viewer(chromium: str, viewer_url: str,
                                                  served_recording: tuple[str, list[str]],
                                                  tmp_path: Path) -> None:
    shot = tmp_path / "viewer.png"
    console: list[str] = []
    with sync_api.sync_playwright() as pw:
        try:
            browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                         args=CHROMIUM_ARGS)
        except sync_api.Error as exc:
            pytest.skip(f"chromium does not start under playwright: {str(exc)[:300]}")
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.on("console", lambda m: console.append(f"{m.type}: {m.text[:300]}"))

            def local_only(route: sync_api.Route) -> None:
                # fonts, version check and telemetry are elsewhere: refuse at once rather
                # than wait on a closed network (a screenshot waits for the fonts)
                host = urllib.parse.urlparse(route.request.url).hostname
                if host in ("127.0.0.1", "localhost"):
                    route.continue_()
                else:
                    route.abort()

            page.route("**/*", local_only)
            page.goto(viewer_url)
            deadline = time.monotonic() + LOAD_TIMEOUT_S
            # the viewer says when the file is read; screenshots before that only slow the
            # wasm start (each waits for a frame from the busy page)
            while not any("has finished" in m for m in console):
                if time.monotonic() > deadline:
                    break
                page.wait_for_timeout(500)
            problems = ["not shot"]
            while problems and time.monotonic() < deadline:
                page.wait_for_timeout(1000)  # a frame or two to lay out and draw the views
                try:
                    page.screenshot(path=str(shot), timeout=30_000)
                except sync_api.TimeoutError:
                    continue
                problems = _judge(np.asarray(Image.open(shot).convert("RGB")))
        finally:
            browser.close()
    _, served = served_recording
    assert any(p.startswith("/review.rrd") for p in served), "the viewer never fetched the file"
    errors = [m for m in console if m.startswith("error") and "Failed to" not in m]
    assert not problems, f"{problems}; screenshot {shot}; console errors {errors[:5]}"
