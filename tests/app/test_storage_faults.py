"""Storage faults answered as 503 + Retry-After in the error shape, /readyz not ready while
they last, and recovery without a restart with nothing lost: a SQLite file on a real full file
system (a small tmpfs) and a PostgreSQL server lost behind a loopback TCP proxy."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url

from app.main import create_app
from app.migrate import upgrade
from tests.app.conftest import Api, make_settings
from tests.conftest import make_series

TEL = "/v1/aircraft/N1/actuators/ema1/telemetry"


def _wait_until(cond: Any, timeout_s: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError("condition not met in time")


def _assert_503(r: Any) -> None:
    assert r.status_code == 503, r.text
    assert r.headers["content-type"] == "application/json"
    assert int(r.headers["retry-after"]) > 0
    body = r.json()
    assert body["error"] == "StorageUnavailable" and isinstance(body["detail"], str), body


def _batch(api: Api, batch_id: str, t0: float, n: int = 20_000, seed: int = 0) -> Any:
    s = make_series(n, seed=seed, t0=t0)
    return api.send_arrow("N1", "ema1", batch_id, s.t_s, {"current": s.current, "voltage": s.voltage}, wait=30.0)


def _applied(api: Api) -> int:
    r = api.get("/v1/aircraft/N1/actuators/ema1/health")
    return int(r.json()["last_applied_seq"]) if r.status_code == 200 else -1


# ----------------------------------------------------------------------------- SQLite disk full
@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 6 MiB tmpfs (needs root, as on the test machines; skipped otherwise)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(mount)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(path: Path) -> None:
    """Write until the file system is full (unbuffered, down to 512-byte writes)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        size = 64 * 1024
        while size >= 512:
            try:
                os.write(fd, b"\xa5" * size)
            except OSError:
                size //= 2
    finally:
        os.close(fd)


def test_sqlite_disk_full_is_503_and_recovers_without_restart(small_disk: Path) -> None:
    url = f"sqlite:///{small_disk / 'fh.db'}"
    upgrade(url)
    settings = make_settings(url, storage_min_free_bytes=128 * 1024, storage_retry_after_s=3)
    with TestClient(create_app(settings)) as client:
        api = Api(client)
        api.setup_actuator()
        assert _batch(api, "b1", 0.0).status_code == 202
        # Ready once every kind's kernels are (a cold numba cache compiles them meanwhile).
        _wait_until(lambda: client.get("/readyz").status_code == 200, timeout_s=300.0)
        _fill(small_disk / "filler")
        r = client.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["storage"].startswith("disk full"), r.text
        assert r.json()["error"] == "NotReady" and "retry-after" in r.headers
        r = _batch(api, "b2", 100.0, seed=1)
        _assert_503(r)
        assert "full" in r.json()["detail"]
        # Nothing of the refused batch is in the log.
        assert _applied(api) == 1
        (small_disk / "filler").unlink()
        r = _batch(api, "b2", 100.0, seed=1)  # the client's retry, same batch id
        assert r.status_code == 202, r.text
        assert r.json()["seq"] == 2
        _wait_until(lambda: client.get("/readyz").status_code == 200)
        assert _batch(api, "b3", 200.0, seed=2).status_code == 202
        _wait_until(lambda: _applied(api) == 3)
        assert len(api.history()) > 0


# ----------------------------------------------------------------------------- PostgreSQL lost
class TcpProxy:
    """127.0.0.1:port -> target, which can be cut (listener closed, every connection reset)
    and brought back on the same port."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = int(s.getsockname()[1])
        self._listener: socket.socket | None = None
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()

    def start(self) -> None:
        ls = socket.socket()
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind(("127.0.0.1", self.port))
        ls.listen(64)
        self._listener = ls
        threading.Thread(target=self._accept, args=(ls,), daemon=True).start()

    def cut(self) -> None:
        if self._listener is not None:
            # close() alone leaves the accept thread blocked on the listening socket, which then
            # still accepts connections (Linux); shutdown() wakes it and stops accepting.
            with contextlib.suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)
            self._listener.close()
            self._listener = None
        with self._lock:
            for c in self._conns:
                with contextlib.suppress(OSError):
                    c.shutdown(socket.SHUT_RDWR)  # wakes the pipe threads blocked in recv
                c.close()
            self._conns.clear()

    def _accept(self, ls: socket.socket) -> None:
        while True:
            try:
                client, _ = ls.accept()
            except OSError:
                return
            upstream = socket.create_connection(self.target)
            with self._lock:
                self._conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(src: socket.socket, dst: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                dst.sendall(data)
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)


@pytest.mark.postgres
def test_postgres_lost_is_503_and_recovers_without_restart(db_url: str) -> None:
    if not db_url.startswith("postgresql"):
        pytest.skip("PostgreSQL only (the SQLite fault is the full disk above)")
    real = make_url(db_url)
    proxy = TcpProxy((real.host or "127.0.0.1", real.port or 5432))
    proxy.start()
    via_proxy = real.set(host="127.0.0.1", port=proxy.port).render_as_string(hide_password=False)
    settings = make_settings(via_proxy, storage_retry_after_s=2, processor_retry_backoff_s=0.2)
    try:
        with TestClient(create_app(settings)) as client:
            api = Api(client)
            api.setup_actuator()
            assert _batch(api, "b1", 0.0).status_code == 202
            proxy.cut()
            _assert_503(_batch(api, "b2", 100.0, seed=1))
            _assert_503(api.get("/v1/aircraft"))
            r = client.get("/readyz")
            assert r.status_code == 503 and r.json()["checks"]["database"].startswith("unreachable"), r.text
            proxy.start()
            r = _batch(api, "b2", 100.0, seed=1)
            assert r.status_code == 202 and r.json()["seq"] == 2, r.text
            _wait_until(lambda: client.get("/readyz").status_code == 200)
            _wait_until(lambda: _applied(api) == 2)
            assert np.isfinite([w["t_end_s"] for w in api.history()]).all()
    finally:
        proxy.cut()
