"""The API docs (/docs Swagger UI, /redoc ReDoc) work offline: every asset they load is
served by covslam itself (the copies the `fastapi-offline` package ships), none comes
from a CDN. Checked in the HTML, over HTTP, and in headless Chromium with every
request to another host refused and recorded."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from typing import Any
from urllib.parse import urljoin, urlsplit

import httpx
import pytest

from tests.e2e.conftest import Server

DOC_PAGES = ("/docs", "/redoc")
ABSOLUTE_URL = re.compile(r"""(?:https?:)?//[\w.-]+""")


class _Refs(HTMLParser):
    """URLs that a page loads: script src, link href, img src, a redoc spec-url."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        for key in ("src", "href", "spec-url"):
            if a.get(key) and (tag != "a" or key != "href"):
                self.urls.append(str(a[key]))


def _refs(html: str) -> list[str]:
    parser = _Refs()
    parser.feed(html)
    return parser.urls


EXPECTED_TYPES = {".js": "javascript", ".css": "text/css", ".png": "image/png", ".json": "json"}


@pytest.mark.parametrize("page", DOC_PAGES)
def test_doc_pages_reference_only_this_server_and_their_assets_load(
    client: httpx.Client, page: str
) -> None:
    r = client.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    policy = dict(d.strip().split(" ", 1) for d in r.headers["content-security-policy"].split(";"))
    assert policy["default-src"] == "'self'"  # and no directive names another host
    assert not any(ABSOLUTE_URL.search(v) or "*" in v for v in policy.values()), policy
    assert ABSOLUTE_URL.findall(r.text) == []  # no host named anywhere in the page
    urls = _refs(r.text)
    assert any(u.endswith(".js") for u in urls), urls  # the UI's bundle
    for url in urls:
        assert not urlsplit(url).netloc, url
        asset = client.get(urljoin(page, url))
        assert asset.status_code == 200, url
        suffix = url[url.rfind(".") :]
        assert EXPECTED_TYPES[suffix] in asset.headers["content-type"], (url, asset.headers)
        assert len(asset.content) > 100, url
    bundle = client.get(next(u for u in urls if u.endswith(".js"))).text
    marker = "SwaggerUIBundle" if page == "/docs" else "Redoc"
    assert marker in bundle


def _open_offline(browser: Any, url: str) -> tuple[Any, list[str], list[str]]:
    """A page on which every request to a host other than `url`'s is aborted."""
    origin = "{0.scheme}://{0.netloc}".format(urlsplit(url))
    elsewhere: list[str] = []
    problems: list[str] = []
    page = browser.new_page(viewport={"width": 1280, "height": 800})

    def route(r: Any) -> None:
        if r.request.url.startswith(origin + "/") or r.request.url.startswith("data:"):
            r.continue_()
        else:
            elsewhere.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("requestfailed", lambda r: problems.append(f"failed: {r.url}"))
    page.goto(url)
    return page, elsewhere, problems


def test_swagger_ui_and_redoc_render_without_other_hosts(browser: Any, server: Server) -> None:
    page, elsewhere, problems = _open_offline(browser, f"{server.url}/docs")
    page.wait_for_selector(".swagger-ui .info .title", timeout=30e3)
    assert "covslam" in page.inner_text(".swagger-ui .info .title")
    page.wait_for_selector(".opblock-summary-path[data-path='/v1/maps/{map_id}/frames']")
    assert page.locator(".opblock").count() >= 15  # every endpoint of REST API v1
    page.close()
    assert elsewhere == [] and problems == []

    page, elsewhere, problems = _open_offline(browser, f"{server.url}/redoc")
    page.wait_for_selector("h1", timeout=30e3)
    assert "covslam" in page.inner_text("h1")
    page.get_by_text("/v1/maps/{map_id}/frames").first.wait_for(state="attached")
    page.wait_for_timeout(500)  # ReDoc adds its maker's logo after the first render
    page.close()
    assert elsewhere == []  # nothing left the browser
    # ReDoc's bundle asks for its logo from a CDN; the page's policy refuses it in the
    # browser (and ReDoc hides the image). Any other problem is a failure.
    logo = "https://cdn.redoc.ly/redoc/logo-mini.svg"
    blocked = ("Content Security Policy", "failed: ")
    assert [p for p in problems if not (logo in p and any(b in p for b in blocked))] == []
