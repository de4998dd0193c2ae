"""The browser the page tests drive: Debian's Chromium, headless, never a downloaded build."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import pytest

from tests.conftest import REPO

if TYPE_CHECKING:  # Playwright is imported by the page tests themselves: a run that collects none (the fast
    from playwright.sync_api import Browser  # loop: every page test is slow) does not pay its import


CHROMIUM = "/usr/bin/chromium"
# No background traffic: the page tests check that no request leaves the service.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SHOTS = REPO / "test-artifacts" / "screenshots"
"""Screenshots every run keeps as artefacts."""


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    from playwright.sync_api import sync_playwright

    SHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()
