"""/docs and /redoc work with no internet: the pages name no external host, every asset they
reference is served by the app, and the browser is told to load nothing from elsewhere."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app

URL_SCHEME = re.compile(r"\b[a-z][a-z0-9+.-]*://", re.IGNORECASE)
CSS_URL = re.compile(r"url\(\s*['\"]?([^'\")]+)", re.IGNORECASE)
#: Hosts docs pages commonly load their scripts, styles and fonts from.
ASSET_HOSTS = ("cdn.jsdelivr.net", "unpkg.com", "cdnjs.cloudflare.com", "fonts.googleapis.com",
               "fonts.gstatic.com", "fastapi.tiangolo.com")


class _Refs(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.refs += [v for k, v in attrs if k in ("src", "href", "spec-url") and v]


@pytest.fixture(scope="module")
def client() -> TestClient:
    return TestClient(create_app(Settings(database_url="sqlite://", warm_kernels=False, processor_enabled=False)))


@pytest.mark.parametrize("page", ["/docs", "/redoc", "/docs/oauth2-redirect"])
def test_docs_pages_name_no_external_host(client: TestClient, page: str) -> None:
    r = client.get(page)
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    assert URL_SCHEME.findall(r.text) == [], "the page names a host"
    csp = r.headers["content-security-policy"]
    assert "default-src 'self'" in csp and not URL_SCHEME.search(csp)
    parser = _Refs()
    parser.feed(r.text)
    for ref in parser.refs:
        assert ref.startswith("/") and not ref.startswith("//"), ref
        asset = client.get(ref)
        assert asset.status_code == 200, ref
        if ref.endswith(".css"):
            assert "@import" not in asset.text
            for url in CSS_URL.findall(asset.text):
                assert url.startswith(("data:", "#")) or not URL_SCHEME.match(url), url
        if ref.endswith(".js"):
            named = [host for host in ASSET_HOSTS if host in asset.text]
            assert named == [], f"{ref} names {named}"


def test_docs_reference_their_assets(client: TestClient) -> None:
    for page, asset in (("/docs", "swagger-ui-bundle.js"), ("/docs", "swagger-ui.css"), ("/redoc", "redoc.standalone.js")):
        parser = _Refs()
        parser.feed(client.get(page).text)
        assert any(ref.endswith(asset) for ref in parser.refs), (page, asset)
    assert '"validatorUrl": null' in client.get("/docs").text  # no validator badge from its host
    assert client.get("/openapi.json").status_code == 200
