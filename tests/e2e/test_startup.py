"""Start-up on a cold numba cache: the service answers while kernels compile, and a SIGTERM
during that first compile ends the server and its compiling children within seconds."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from fleethealth_client import FleetHealthClient

from tests.e2e.conftest import LiveServer

pytestmark = pytest.mark.e2e

# Generous for a busy two-core machine; a cold compile of every kind takes a minute of CPU or
# more, and the server used to wait for it.
EXIT_BOUND_S = 20.0
WAIT_S = 300.0


def _processes_with_env(marker: str) -> list[int]:
    """Pids of this user's processes whose environment holds ``marker``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        with contextlib.suppress(OSError):
            if marker.encode() in (entry / "environ").read_bytes():
                found.append(int(entry.name))
    return found


def _readyz(server: LiveServer) -> dict[str, Any] | None:
    with contextlib.suppress(httpx.HTTPError, ValueError):
        r = httpx.get(f"{server.url}/readyz", timeout=2.0)
        body: dict[str, Any] = r.json()
        return body
    return None


def test_sigterm_during_cold_compile(tmp_path: Path) -> None:
    from app.migrate import upgrade

    url = f"sqlite:///{tmp_path / 'e2e.db'}"
    upgrade(url)
    cache = str(tmp_path / "numba-cache")
    server = LiveServer(url, tmp_path / "server.log", extra_env={"NUMBA_CACHE_DIR": cache})
    server.launch()
    assert server.proc is not None
    try:
        deadline = time.monotonic() + WAIT_S
        body = None
        while time.monotonic() < deadline and server.proc.poll() is None:
            body = _readyz(server)
            if body and any(k["status"] == "compiling" for k in body["kernels"].values()):
                break
            time.sleep(0.1)
        assert body is not None, f"server never answered; see {server.log_path}"
        assert body["checks"]["database"] == "ok"
        compiling = [kind for kind, k in body["kernels"].items() if k["status"] == "compiling"]
        assert compiling, body
        assert set(_processes_with_env(cache)) - {server.proc.pid}, "no compiling child found"
        # The service answers while it compiles; the client reads the 503 body as it is.
        assert httpx.get(f"{server.url}/healthz", timeout=10.0).status_code == 200
        with FleetHealthClient(server.url, server.api_key) as client:
            assert client.readiness()["status"] == "not ready"

        t0 = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        server.proc.wait(EXIT_BOUND_S)
        print(f"server exited {time.monotonic() - t0:.2f} s after SIGTERM (compiling {compiling})")
        deadline = time.monotonic() + EXIT_BOUND_S
        while _processes_with_env(cache) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _processes_with_env(cache), "compiling children outlived the server"
    finally:
        server.stop()


def _tails_with_data(url: str, key: str) -> set[str]:
    with contextlib.suppress(httpx.HTTPError, ValueError, KeyError):
        r = httpx.get(f"{url}/v1/fleet/health", headers={"Authorization": f"Bearer {key}"}, timeout=5.0)
        return {
            a["tail"] for a in r.json()["aircraft"] if any(x["last_applied_seq"] > 0 for x in a["actuators"])
        }
    return set()


def test_demo_fills_the_fleet_and_stops_with_its_feeder(tmp_path: Path) -> None:
    """``serve --demo``: three aircraft get applied data, the request log stays off, the demo's
    own lines show, and SIGTERM ends the server and its simulator child."""
    key = "e2e-demo-key-0123456789abcdef"
    server = LiveServer(f"sqlite:///{tmp_path / 'demo.db'}", tmp_path / "server.log",
                        extra_env={"FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": key})
    server.launch(["--demo", "--log-level", "info"])
    assert server.proc is not None
    try:
        deadline = time.monotonic() + WAIT_S
        tails: set[str] = set()
        while time.monotonic() < deadline and server.proc.poll() is None and len(tails) < 3:
            tails = _tails_with_data(server.url, key)
            time.sleep(0.5)
        assert tails == {"FH-001", "FH-002", "FH-003"}, f"see {server.log_path}"
        feeders = [pid for pid in _processes_with_env(key) if pid != server.proc.pid]
        assert feeders, "no simulator child"
        server.proc.send_signal(signal.SIGTERM)
        server.proc.wait(EXIT_BOUND_S)
        deadline = time.monotonic() + EXIT_BOUND_S
        while set(_processes_with_env(key)) & set(feeders) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not set(_processes_with_env(key)) & set(feeders), "the simulator outlived the server"
    finally:
        server.stop()
    log = server.log_path.read_text()
    assert "the demo fleet belongs to operator 'default'" in log
    assert "simulate: FH-001/ema-left" in log
    assert "POST /v1/" not in log  # no request log in the demo
