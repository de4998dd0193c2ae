"""The browser the page tests drive: Debian's Chromium, headless, never a downloaded build."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, sync_playwright

from tests.conftest import REPO

CHROMIUM = "/usr/bin/chromium"
# No background traffic: the page tests check that no request leaves the service.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SHOTS = REPO / "test-artifacts" / "screenshots"
"""Screenshots every run keeps as artefacts."""


@pytest.fixture(scope="session")
def browser() -> Iterator[Browser]:
    """One Chromium per test process (each test opens its own context: no cookie, storage or page is
    shared between tests); a launch costs about a second of CPU, paid once instead of once per module."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module", autouse=True)
def pages_closed_after_module(browser: Browser) -> Iterator[None]:
    """A module's pages do not outlive it in the session's browser: what it leaves open (a page still
    polling a cell that has stopped) is closed when the module ends, as the module's own browser was."""
    before = set(browser.contexts)
    yield
    for context in browser.contexts:
        if context not in before:
            context.close()
