"""Kernels prepared kind by kind: each kind's streams are applied once that kind is ready, the
others wait (durably logged); ``/readyz`` shows each kind; compiling children die on stop."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

import app.kernels
import app.main
from app.kernels import KernelWarmup, warm_kind
from app.main import create_app
from tests.app.conftest import Api, make_settings
from tests.conftest import make_series

# Generous bounds for a busy two-core machine; every loop below ends as soon as its condition holds.
WAIT_S = 120.0


def _until(predicate: Any, timeout_s: float = WAIT_S, what: str = "condition") -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} not reached within {timeout_s} s")


def test_each_kind_applies_once_ready(db_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()

    def warm(kind: str) -> None:
        if kind == "deterioration_ekf" and not release.wait(WAIT_S):
            raise RuntimeError("test never released the kind")
        warm_kind(kind)

    real = app.main.KernelWarmup

    def in_thread(kinds: list[str], **kw: Any) -> KernelWarmup:
        return real(kinds, **{**kw, "processes": 0, "warm": warm})

    monkeypatch.setattr(app.main, "KernelWarmup", in_thread)
    with TestClient(create_app(make_settings(db_url))) as client:
        api = Api(client)
        api.setup_actuator("N1", "ema1")
        r = api.post("/v1/aircraft/N1/actuators", json={"actuator_id": "drive", "kind": "friction_drive"})
        assert r.status_code == 201, r.text
        kernels = api.app.state.kernels
        _until(lambda: kernels.snapshot()["fakf"]["status"] == "ready", what="fakf ready")

        n = 400
        t = np.arange(n) * 1e-3
        rng = np.random.default_rng(1)
        drive = {"current": np.full(n, 20.0), "motor_speed": rng.standard_normal(n), "wheel_speed": rng.standard_normal(n)}
        r = api.send_arrow("N1", "drive", "d1", t, drive, wait=0.5)
        assert r.status_code == 202, r.text  # logged while its kind compiles
        s = make_series(600, seed=4)
        r = api.send_arrow("N1", "ema1", "e1", s.t_s, {"current": s.current, "voltage": s.voltage})
        assert r.status_code == 202, r.text
        assert api.health("N1", "ema1")["last_applied_seq"] == 1
        assert api.health("N1", "drive")["last_applied_seq"] == 0

        ready = client.get("/readyz")
        assert ready.status_code == 503
        body = ready.json()
        assert body["checks"]["database"] == "ok"
        assert body["kernels"]["fakf"]["status"] == "ready"
        assert body["kernels"]["deterioration_ekf"]["status"] == "compiling"
        assert "deterioration_ekf compiling" in body["checks"]["kernels"]

        release.set()
        _until(lambda: api.health("N1", "drive")["last_applied_seq"] == 1, what="drive applied")
        _until(lambda: client.get("/readyz").status_code == 200, what="all kinds ready")
        assert all(k["status"] == "ready" for k in client.get("/readyz").json()["kernels"].values())


def test_stop_kills_a_compiling_child(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app.kernels, "stamp_dir", lambda: tmp_path)
    pid_file = tmp_path / "pid"
    slow = f"import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(600)"
    kernels = KernelWarmup(["fakf"], processes=1, child_command=lambda kind: [sys.executable, "-c", slow])
    kernels.start()
    pid = int(_until(lambda: pid_file.exists() and pid_file.read_text(), what="child started"))
    assert kernels.snapshot()["fakf"]["status"] == "compiling"
    assert kernels.applicable_kinds() == frozenset()
    kernels.stop()

    def gone() -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        return False

    _until(gone, timeout_s=30.0, what="child killed")
    assert not kernels.done.is_set()


def test_a_stamped_kind_loads_in_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The first start compiles in a child and stamps the kind; the next loads it in-process."""
    monkeypatch.setattr(app.kernels, "stamp_dir", lambda: tmp_path)
    spawned: list[str] = []
    warmed: list[str] = []

    def child(kind: str) -> list[str]:
        spawned.append(kind)
        return [sys.executable, "-c", "pass"]

    for _ in range(2):
        kernels = KernelWarmup(["fakf"], processes=1, child_command=child, warm=warmed.append)
        kernels.start()
        assert kernels.done.wait(WAIT_S)
        assert kernels.all_ready() and kernels.applicable_kinds() is None
    assert spawned == ["fakf"]
    assert warmed == ["fakf", "fakf"]


def test_a_failed_child_falls_back_and_reports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app.kernels, "stamp_dir", lambda: tmp_path)

    def broken(kind: str) -> None:
        raise ValueError(f"no kernels for {kind}")

    kernels = KernelWarmup(
        ["fakf"], processes=1, warm=broken,
        child_command=lambda kind: [sys.executable, "-c", "raise SystemExit(5)"],
    )
    kernels.start()
    assert kernels.done.wait(WAIT_S)
    status = kernels.snapshot()["fakf"]
    assert status["status"] == "failed"
    assert "no kernels for fakf" in status["error"]
    assert kernels.applicable_kinds() is None  # its streams are applied (and fail visibly)
    assert not kernels.all_ready()


def test_child_exits_when_its_parent_goes() -> None:
    """The server keeps the child's stdin open; once it closes the child exits at once."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.kernels", "--exit-on-stdin-eof", "stmmae"],
        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(WAIT_S) == 3


def _waits_for_a_lock(pid: int) -> bool:
    """Whether process ``pid`` is queued behind a file lock (Linux ``/proc/locks``, ``->``)."""
    return any("->" in line and f" {pid} " in f" {line} " for line in Path("/proc/locks").read_text().splitlines())


def test_a_child_waits_for_the_compile_lock_then_skips_a_kind_stamped_meanwhile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Processes starting together on a cold cache compile a kind once: a second compiling child
    queues behind the first's lock and, once the kind is stamped, loads nothing and exits."""
    monkeypatch.setattr(app.kernels, "stamp_dir", lambda: tmp_path)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}  # the child's stamp_dir
    with app.kernels.compile_lock("fakf"):  # as a first child compiling fakf holds it
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.kernels", "fakf"], env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )
        _until(lambda: _waits_for_a_lock(proc.pid) or proc.poll() is not None, what="child queued")
        assert proc.poll() is None, "the child did not wait for the lock"
        app.kernels.write_stamp(tmp_path, "fakf", app.kernels.sources_fingerprint())
    assert proc.wait(WAIT_S) == 0, proc.stderr.read() if proc.stderr else ""
    assert not list(tmp_path.rglob("*.nbi")), "the child compiled a kind stamped while it waited"
