"""Fixtures of the end-to-end tests: a real ``nlpsf serve`` per module and the page loaded in headless
Chromium. A module that needs its own service (jobs, restarts) defines its own ``server``; ``page`` uses it."""

from __future__ import annotations

import os
import shutil
import signal
import tempfile

import pytest

from ..servers import free_port, start_server
from .browser import ARTIFACTS, CHROMIUM, FLAGS, browser_missing


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    directory = tmp_path_factory.mktemp("e2e")
    port = free_port()
    process = start_server(directory / "jobs.sqlite3", port, log=directory / "server.log")
    yield f"http://127.0.0.1:{port}/"
    process.send_signal(signal.SIGTERM)
    process.wait(20)


@pytest.fixture(scope="module")
def page(server):
    missing = browser_missing()
    if missing:
        if os.environ.get("CI"):
            pytest.fail(f"browser tests must run in CI: {missing}")
        pytest.skip(missing)
    from playwright.sync_api import sync_playwright

    ARTIFACTS.mkdir(exist_ok=True)
    profile = tempfile.mkdtemp(prefix="nlpsf-chromium-")
    errors: list[str] = []
    with sync_playwright() as playwright:
        # A persistent context is how Playwright takes a --user-data-dir: a fresh one per run.
        context = playwright.chromium.launch_persistent_context(
            profile,
            executable_path=CHROMIUM,
            headless=True,
            args=FLAGS,
            viewport={"width": 1280, "height": 1000},
            accept_downloads=True,
        )
        tab = context.new_page()
        tab.on("pageerror", lambda error: errors.append(str(error)))
        tab.goto(server)
        tab.wait_for_selector("body[data-ready='true']", timeout=30_000)
        yield tab
        tab.screenshot(path=str(ARTIFACTS / "e2e-page.png"), full_page=True)
        context.close()
    shutil.rmtree(profile, ignore_errors=True)
    assert not errors, f"JavaScript errors on the page: {errors}"
