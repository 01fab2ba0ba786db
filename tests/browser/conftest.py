"""Browser test fixtures: the real server in a subprocess and Debian's Chromium under Playwright.

The server is started exactly as an operator would (``python -m app serve``)
on free ports with a fresh database, with its 3D view on another free port.
Chromium is Debian's package (``/usr/bin/chromium``; tests/setup_and_run.sh
installs it), driven headless with software WebGL.  Screenshots go to
``test-artifacts/screenshots/`` (outside git).
"""

from __future__ import annotations

import json
import os
import shutil
import urllib.request
from pathlib import Path

import pytest

from app.bench.server import free_port, start_server, stop_server, wait_ready

REPO = Path(__file__).resolve().parents[2]
SAMPLES = REPO / "sample_telemetry"
SCREENSHOTS = REPO / "test-artifacts" / "screenshots"
CHROMIUM = os.environ.get("STARID_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--disable-gpu-sandbox",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run"]
#: The catalogue and index load before the server listens; a cold first start builds the index.
SERVER_START_TIMEOUT_S = 180
VIEWPORT = {"width": 1280, "height": 800}


def api_json(base: str, path: str, method: str = "GET", body: dict | None = None, raw: bytes | None = None,
             content_type: str = "application/json"):
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    req = urllib.request.Request(base + path, data=data, method=method,
                                 headers={"Content-Type": content_type} if data is not None else {})
    with urllib.request.urlopen(req, timeout=60) as response:
        return json.loads(response.read())


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """Base URL of a running ``python -m app serve`` with its 3D view; stopped after the session."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: run tests/setup_and_run.sh (it installs Debian's chromium)")
    tmp = tmp_path_factory.mktemp("console")
    port, viewer_port = free_port(), free_port()
    log_path = tmp / "server.log"
    proc = start_server(tmp / "console.sqlite3", port, log_path,
                        ("--viewer-port", str(viewer_port), "--log-level", "warning"))
    try:
        try:
            wait_ready(port, proc, log_path, timeout_s=SERVER_START_TIMEOUT_S)
        except RuntimeError as exc:
            pytest.fail(str(exc))
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


@pytest.fixture(scope="session")
def api(server):
    """``api(path, method="GET", body=None, raw=None)``: a JSON call to the running server."""
    def call(path: str, method: str = "GET", body: dict | None = None, raw: bytes | None = None):
        return api_json(server, path, method, body, raw)
    return call


@pytest.fixture(scope="session")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield chromium
        finally:
            chromium.close()


class WatchedPage:
    """A page whose console errors and uncaught exceptions are collected."""

    def __init__(self, page) -> None:
        self.page = page
        self.errors: list[str] = []
        page.on("console", lambda m: self.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))

    def screenshot(self, name: str, full_page: bool = False) -> Path:
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        path = SCREENSHOTS / f"{name}.png"
        self.page.screenshot(path=str(path), full_page=full_page)
        return path


@pytest.fixture
def new_page(browser):
    """Factory of fresh pages, 1280x800 unless ``width``/``height`` say otherwise (own browser context each,
    so own sessionStorage: each is a console session of its own; downloads accepted); closed after the test."""
    contexts = []

    def make(width: int = VIEWPORT["width"], height: int = VIEWPORT["height"]) -> WatchedPage:
        context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
        contexts.append(context)
        return WatchedPage(context.new_page())

    yield make
    for context in contexts:
        context.close()


@pytest.fixture(scope="session", autouse=True)
def _clean_screenshots():
    if SCREENSHOTS.exists():
        shutil.rmtree(SCREENSHOTS)
    yield
