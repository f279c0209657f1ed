"""/docs and /redoc render in Chromium with every host but 127.0.0.1 unreachable."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.e2e.conftest import LiveServer

pytestmark = pytest.mark.e2e

CHROMIUM = "/usr/bin/chromium"


@pytest.mark.skipif(shutil.which(CHROMIUM) is None, reason="needs Debian's chromium")
@pytest.mark.parametrize(("page", "rendered"), [("/docs", "opblock-summary-path"), ("/redoc", "operation-type")])
def test_docs_render_offline(live_server: LiveServer, tmp_path: Path, page: str, rendered: str) -> None:
    proc = subprocess.run(
        [
            CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={tmp_path}",
            # Offline: every name but the server's address fails to resolve.
            "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
            "--virtual-time-budget=20000", "--dump-dom", f"{live_server.url}{page}",
        ],
        capture_output=True, text=True, timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    dom = proc.stdout
    assert rendered in dom, "the page did not render the API's operations"
    assert "/v1/fleet/health" in dom and "readyz" in dom
