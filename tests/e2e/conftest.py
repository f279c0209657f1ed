"""A real ``fleethealth serve`` process on 127.0.0.1, which tests can kill and restart."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.conftest import migrated_sqlite

ROOT = Path(__file__).resolve().parents[2]
FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")
E2E_KEY = "e2e-admin-key-0123456789abcdef"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    def __init__(self, db_url: str, log_path: Path, extra_env: dict[str, str] | None = None) -> None:
        self.db_url = db_url
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.api_key = E2E_KEY
        self.log_path = log_path
        self.extra_env = extra_env or {}
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 300.0) -> None:
        # Bounded but generous: with a cold numba cache the first server compiles every kernel
        # before /readyz answers, which takes minutes on a busy two-core machine.
        self.launch()
        assert self.proc is not None
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}; see {self.log_path}")
            with contextlib.suppress(httpx.HTTPError):  # not listening yet
                if httpx.get(f"{self.url}/readyz", timeout=1.0).status_code == 200:
                    return
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"server not ready within {timeout_s} s; see {self.log_path}")

    def launch(self, args: list[str] | None = None) -> None:
        """Start the process without waiting for it (``args`` replace ``--log-level warning``)."""
        env = {
            **os.environ,
            "FLEETHEALTH_DATABASE_URL": self.db_url,
            "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": self.api_key,
            "FLEETHEALTH_PROCESSOR_SCAN_INTERVAL_S": "0.2",
            **self.extra_env,
        }
        log = open(self.log_path, "ab")  # noqa: SIM115 (closed with the process)
        self.proc = subprocess.Popen(
            [FLEETHEALTH, "serve", "--host", "127.0.0.1", "--port", str(self.port),
             *(args if args is not None else ["--log-level", "warning"])],
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
        )

    def kill(self) -> None:
        """SIGKILL: no shutdown handler runs."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.api_key}"}


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[LiveServer]:
    """A migrated SQLite file served by a real uvicorn process."""
    server = LiveServer(migrated_sqlite(tmp_path / "e2e.db"), tmp_path / "server.log")
    server.start()
    yield server
    server.stop()
