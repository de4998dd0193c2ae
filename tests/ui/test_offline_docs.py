"""Offline API docs: ``/docs`` (Swagger UI) and ``/redoc`` render in headless Chromium with every
request going to the service itself (a plant network has no CDN)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Browser

from tests.conftest import Served, start_served, stop_served
from tests.ui.conftest import SHOTS


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("docs"))
    try:
        yield s
    finally:
        stop_served(s)


def test_docs_html_references_only_local_assets(served: Served) -> None:
    for path in ("/docs", "/redoc"):
        r = httpx.get(served.base_url + path)
        assert r.status_code == 200
        refs = re.findall(r"""(?:src|href|url)\s*[=:]\s*['"]([^'"]+)['"]""", r.text)
        assert refs, r.text
        assert all(ref.startswith("/") and not ref.startswith("//") for ref in refs), refs
        assert "cdn" not in r.text.lower() and "googleapis" not in r.text
        for ref in refs:
            if ref.startswith("/docs/assets/"):
                a = httpx.get(served.base_url + ref)
                assert a.status_code == 200 and len(a.content) > 1000, ref
    assert httpx.get(served.base_url + "/docs/assets/../../cell.py").status_code == 404


@pytest.mark.parametrize(("path", "ready"), [("/docs", ".swagger-ui .opblock"), ("/redoc", "[role=menuitem]")])
def test_docs_render_in_chromium_without_leaving_the_service(served: Served, browser: Browser, path: str,
                                                             ready: str) -> None:
    context = browser.new_context()
    outside: list[str] = []

    def route(r: object) -> None:
        url = r.request.url  # type: ignore[attr-defined]
        if url.startswith(served.base_url) or url.startswith("data:") or url.startswith("blob:"):
            r.continue_()  # type: ignore[attr-defined]
        else:
            outside.append(url)
            r.abort()  # type: ignore[attr-defined]

    context.route("**/*", route)
    page = context.new_page()
    try:
        page.goto(served.base_url + path)
        page.wait_for_selector(ready, timeout=30_000)
        text = page.inner_text("body")
        assert "cellctl" in text
        assert "/calibrations/{cal_id}/activate" in text or "Activate" in text
        page.screenshot(path=str(Path(SHOTS) / f"docs{path.replace('/', '-')}.png"))
    finally:
        context.close()
    assert outside == []
