"""The tools wait for a server however long its kernels take, with progress lines; a busy port
ends ``fleethealth serve`` with one clear line."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

from fleethealth_client import FleetHealthClient

from fleethealth_tools import readiness
from fleethealth_tools.readiness import KernelProgress, describe, wait_for_server

FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")


def _body(database: str = "ok", **kinds: str) -> dict[str, Any]:
    return {
        "checks": {"database": database, "schema": "ok"},
        "kernels": {kind: {"status": status, "seconds": 3.0} for kind, status in kinds.items()},
    }


class _Server:
    """Answers /readyz with the bodies given, one per poll (the last one repeats)."""

    def __init__(self, bodies: list[dict[str, Any] | None]) -> None:
        self._bodies: Iterator[dict[str, Any] | None] = iter(bodies)
        self.last: dict[str, Any] | None = None
        self.polls = 0

    def readiness(self) -> dict[str, Any]:
        self.polls += 1
        self.last = next(self._bodies, self.last)
        if self.last is None:
            raise ConnectionError("refused")
        return self.last


def _client(server: _Server) -> FleetHealthClient:
    return cast(FleetHealthClient, server)


def test_waits_past_any_fixed_limit_for_its_kinds(monkeypatch: Any) -> None:
    monkeypatch.setattr(readiness, "POLL_S", 0.0)
    bodies: list[dict[str, Any] | None] = [None, None, _body("unreachable: OperationalError")]
    bodies += [_body(fakf="compiling", stmmae="waiting")] * 50
    bodies += [_body(fakf="ready", stmmae="compiling")] * 50 + [_body(fakf="ready", stmmae="ready")]
    server = _Server(bodies)
    lines: list[str] = []
    body = wait_for_server(_client(server), kinds={"stmmae"}, log=lines.append, progress_every_s=0.0)
    assert body is not None and body["kernels"]["stmmae"]["status"] == "ready"
    assert server.polls == len(bodies)
    assert any("server not answering yet" in line for line in lines)
    assert any("stmmae compiling (3 s)" in line for line in lines)
    assert lines[-1].startswith("server ready after")


def test_telemetry_accepted_is_enough_without_kinds(monkeypatch: Any) -> None:
    monkeypatch.setattr(readiness, "POLL_S", 0.0)
    server = _Server([None, _body(fakf="compiling")])
    assert wait_for_server(_client(server), log=lambda _: None) is not None
    assert server.polls == 2


def test_gives_up_only_when_told(monkeypatch: Any) -> None:
    monkeypatch.setattr(readiness, "POLL_S", 0.0)
    lines: list[str] = []
    server = _Server([None])
    assert wait_for_server(_client(server), timeout_s=0.05, log=lines.append) is None
    assert lines and "not ready after" in lines[-1]


def test_failed_kind_ends_the_wait_with_its_reason() -> None:
    body = _body(fakf="failed")
    body["kernels"]["fakf"]["error"] = "TypingError: boom"
    server = _Server([body])
    assert wait_for_server(_client(server), kinds=None, log=lambda _: None) is body
    assert describe(body) == "fakf failed (3 s): TypingError: boom"


def test_progress_lines_until_settled(monkeypatch: Any) -> None:
    monkeypatch.setattr(readiness, "FIRST_PROGRESS_S", 0.0)
    server = _Server([_body(fakf="ready", stmmae="compiling"), _body(fakf="ready", stmmae="ready")])
    lines: list[str] = []
    progress = KernelProgress(_client(server), {"fakf", "stmmae"}, log=lines.append, progress_every_s=0.0)
    for _ in range(4):
        progress.check()
    assert len(lines) == 2
    assert "stmmae compiling" in lines[0] and "logged meanwhile" in lines[0]
    assert lines[1].startswith("kernels ready")
    assert progress.settled


def test_busy_port_is_one_line_and_exit_1(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = subprocess.run(
            [FLEETHEALTH, "serve", "--port", str(port)],
            capture_output=True, text=True, timeout=120, cwd=tmp_path,
        )
    assert proc.returncode == 1
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert f"cannot listen on 127.0.0.1:{port}" in lines[0] and "in use" in lines[0]
    assert not (tmp_path / "data").exists()  # nothing was migrated or written
