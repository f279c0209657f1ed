"""The dashboard page and everything it loads come from the app: no external host is named."""

from __future__ import annotations

import re
from typing import Any

from app.dashboard.router import CSP, STATIC

URL = re.compile(r"[a-z][a-z0-9+.-]*://", re.IGNORECASE)
REFERENCE = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|from\s+["']([^"']+)["']|url\(\s*["']?([^"')]+)""")
BLOCK_COMMENT = re.compile(r"/\*.*?\*/", re.DOTALL)


def _assets(api: Any, path: str, seen: dict[str, str]) -> None:
    """Fetch ``path`` and, recursively, every same-origin file it references."""
    if path in seen:
        return
    r = api.c.get(path)
    assert r.status_code == 200, (path, r.status_code)
    seen[path] = r.text
    for m in REFERENCE.finditer(r.text):
        ref = next(g for g in m.groups() if g)
        if ref.startswith("data:") or ref.startswith("#"):
            continue
        assert ref.startswith("/"), f"{path} references {ref!r}, not a path on this server"
        _assets(api, ref, seen)


def test_the_page_and_its_assets_name_no_external_host(api: Any) -> None:
    r = api.c.get("/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    # The browser may load nothing from elsewhere, whatever a script tried.
    csp = r.headers["content-security-policy"]
    assert csp == CSP and "default-src 'self'" in csp and "connect-src 'self'" in csp
    seen: dict[str, str] = {}
    _assets(api, "/", seen)
    assert {"/", "/dashboard/app.js", "/dashboard/charts.js", "/dashboard/vendor/uPlot.iife.min.js",
            "/dashboard/vendor/uPlot.min.css", "/dashboard/style.css"} <= set(seen)
    for path, text in seen.items():
        # The chart library's minified build keeps one comment, its licence header with the
        # project's address: comments load nothing, code and markup must name no host.
        code = BLOCK_COMMENT.sub("", text) if path.startswith("/dashboard/vendor/") else text
        assert not URL.search(code), f"{path} names a host: {URL.search(code)}"


def test_every_static_file_is_reachable_from_the_page(api: Any) -> None:
    seen: dict[str, str] = {}
    _assets(api, "/", seen)
    shipped = {f"/dashboard/{p.relative_to(STATIC).as_posix()}" for p in STATIC.rglob("*")
               if p.is_file() and p.suffix in (".js", ".css")}
    assert shipped <= set(seen), f"shipped but never loaded: {shipped - set(seen)}"


def test_the_page_needs_no_key_but_the_data_does(api: Any) -> None:
    assert api.c.get("/dashboard/app.js").status_code == 200
    assert api.c.get("/v1/fleet/health").status_code == 401
    assert api.c.get("/dashboard/../app/main.py").status_code == 404


def test_without_the_chart_library_the_page_says_how_to_install_it(api: Any, monkeypatch: Any,
                                                                     tmp_path: Any) -> None:
    from app.dashboard import router

    monkeypatch.setattr(router, "CHART_LIBRARY", tmp_path / "missing.js")
    r = api.c.get("/")
    assert r.status_code == 503 and "make" in r.text and "npm ci" in r.text
