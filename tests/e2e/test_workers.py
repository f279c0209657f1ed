"""Scale-out on PostgreSQL: 2 stateless API processes and 2 ``fleethealth worker`` processes on
loopback (the commands of docker/compose.yaml). A worker is SIGKILLed mid-stream; nothing is lost
or applied twice, and a fleet-event subscriber on the other API process sees every apply."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
import pytest
from fleethealth_client import FleetHealthClient
from websockets.asyncio.client import connect

from tests.conftest import make_series, migrated_pg_schema
from tests.e2e.conftest import E2E_KEY, FLEETHEALTH, ROOT, LiveServer

pytestmark = [pytest.mark.e2e, pytest.mark.postgres]

FAKF = {"fakf": {"identification_samples": 500, "health_window_samples": 500}}
N_BATCHES = 30
BATCH = 500
TAIL = "SCALE"
# API processes are stateless: the processor runs in the workers only.
API_ENV = {"FLEETHEALTH_PROCESSOR_ENABLED": "false"}


class Worker:
    """A ``fleethealth worker`` process."""

    def __init__(self, db_url: str, log_path: Path) -> None:
        self.db_url = db_url
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 300.0) -> None:
        env = {
            **os.environ,
            "FLEETHEALTH_DATABASE_URL": self.db_url,
            "FLEETHEALTH_PROCESSOR_SCAN_INTERVAL_S": "0.5",
        }
        log = open(self.log_path, "ab")  # noqa: SIM115 (closed with the process)
        self.proc = subprocess.Popen([FLEETHEALTH, "worker"], env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"worker exited with {self.proc.returncode}; see {self.log_path}")
            if b"fleethealth worker" in self.log_path.read_bytes():
                return
            time.sleep(0.2)
        raise RuntimeError(f"worker not ready within {timeout_s} s; see {self.log_path}")

    def kill(self) -> None:
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


@pytest.fixture
def pg_schema_url() -> Iterator[str]:
    """A fresh, migrated schema in the test PostgreSQL."""
    with migrated_pg_schema() as url:
        yield url


@pytest.fixture
def cluster(pg_schema_url: str, tmp_path: Path) -> Iterator[tuple[list[LiveServer], list[Worker]]]:
    apis = [LiveServer(pg_schema_url, tmp_path / f"api{k}.log", API_ENV) for k in range(2)]
    workers = [Worker(pg_schema_url, tmp_path / f"worker{k}.log") for k in range(2)]
    try:
        for w in workers:
            w.start()
        for a in apis:
            a.start()
        yield apis, workers
    finally:
        for a in apis:
            a.stop()
        for w in workers:
            w.stop()


def _post(server: LiveServer, act: str, k: int, series: Any, wait_s: float = 0.0) -> dict[str, Any]:
    sl = slice(k * BATCH, (k + 1) * BATCH)
    with FleetHealthClient(server.url, server.api_key) as client:
        return client.post_batch(
            TAIL, act, f"b{k:03d}", {"current": series.current[sl], "voltage": series.voltage[sl]},
            t_s=series.t_s[sl], fmt="arrow", wait_s=wait_s,
        )


def _health(server: LiveServer, act: str) -> dict[str, Any]:
    r = httpx.get(f"{server.url}/v1/aircraft/{TAIL}/actuators/{act}/health", headers=server.headers, timeout=10)
    r.raise_for_status()
    return r.json()  # type: ignore[no-any-return]


def _wait_applied(server: LiveServer, act: str, seq: int, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if _health(server, act)["last_applied_seq"] >= seq:
            return
        time.sleep(0.1)
    raise AssertionError(f"{act}: not applied up to {seq} within {timeout_s} s")


def _results(server: LiveServer, act: str) -> tuple[list[Any], dict[str, Any]]:
    base = f"{server.url}/v1/aircraft/{TAIL}/actuators/{act}"
    hist = httpx.get(f"{base}/health/history", headers=server.headers, timeout=30).json()["items"]
    out = httpx.get(f"{base}/outputs?estimator=fakf&max_samples=1000000", headers=server.headers, timeout=30).json()
    return hist, out


class FleetSubscriber:
    """A thread holding a fleet-event WebSocket (``types=applied,status_changed``)."""

    def __init__(self, server: LiveServer) -> None:
        self.url = server.url.replace("http://", "ws://") + "/v1/fleet/events?types=applied,status_changed"
        self.events: list[dict[str, Any]] = []
        self.ready = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    async def _run(self) -> None:
        async with connect(self.url, additional_headers={"Authorization": f"Bearer {E2E_KEY}"}) as ws:
            while not self._stop.is_set():
                with contextlib.suppress(TimeoutError):
                    msg = orjson.loads(await asyncio.wait_for(ws.recv(), 0.5))
                    if msg["type"] == "ready":
                        self.ready.set()
                    else:
                        self.events.append(msg)

    def __enter__(self) -> FleetSubscriber:
        self._thread.start()
        assert self.ready.wait(30), "fleet subscription not ready"
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    def applied_seqs(self, act: str) -> list[int]:
        return [e["seq"] for e in self.events if e["type"] == "applied" and e["actuator_id"] == act]


def test_two_apis_two_workers_sigkill_a_worker_mid_stream(cluster: tuple[list[LiveServer], list[Worker]]) -> None:
    (api_a, api_b), (worker_1, worker_2) = cluster
    series = make_series(N_BATCHES * BATCH, seed=31)
    acts = ["k1", "k2", "k3"]
    with FleetHealthClient(api_a.url, api_a.api_key) as client:
        client.create_aircraft(TAIL)
        for act in ["reference", *acts]:
            client.create_actuator(TAIL, act, estimators=FAKF)

    # Uninterrupted reference, through API A; ?wait= on API A is answered by a worker's apply.
    for k in range(N_BATCHES):
        _post(api_a, "reference", k, series)
    _wait_applied(api_a, "reference", N_BATCHES)

    with FleetSubscriber(api_b) as sub:
        # Batches alternate between the two API processes; a worker dies mid-stream.
        for k in range(N_BATCHES):
            for act in acts:
                _post(api_a if (k + acts.index(act)) % 2 else api_b, act, k, series)
            if k == N_BATCHES // 3:
                worker_1.kill()
            if k == 2 * N_BATCHES // 3:
                worker_1.start()  # a replacement joins; worker 2 carried the streams meanwhile
                worker_2.kill()
        # ?wait= on the API process that did not log the batch: its waiter is resolved by the
        # worker's notification, not by a poll.
        for act in acts:
            body = _post(api_b, act, N_BATCHES - 1, series, wait_s=60)  # a retry: the first answer
            assert body["seq"] == N_BATCHES
        for act in acts:
            _wait_applied(api_b, act, N_BATCHES)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and any(len(sub.applied_seqs(a)) < N_BATCHES for a in acts):
            time.sleep(0.1)

    ref_hist, ref_out = _results(api_a, "reference")
    assert len(ref_hist) == N_BATCHES * BATCH // 500
    for act in acts:
        h = _health(api_b, act)
        assert h["last_logged_seq"] == h["last_applied_seq"] == N_BATCHES  # nothing lost
        got_hist, got_out = _results(api_b, act)
        # Applied exactly once, in order: the outputs are those of the uninterrupted run.
        assert [(w["t_start_s"], w["indicators"], w["status"]) for w in got_hist] == [
            (w["t_start_s"], w["indicators"], w["status"]) for w in ref_hist]
        assert got_out["t_s"] == ref_out["t_s"]
        for name in ref_out["series"]:
            np.testing.assert_array_equal(
                np.array(ref_out["series"][name], dtype=float), np.array(got_out["series"][name], dtype=float))
        # The subscriber on API B heard of every batch applied by the workers, each once.
        assert sorted(sub.applied_seqs(act)) == list(range(1, N_BATCHES + 1)), act


def test_compose_runs_the_commands_of_this_test() -> None:
    """docker/compose.yaml (no Docker engine here) runs what the cluster fixture runs."""
    import yaml

    services = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())["services"]
    apis = [s for s in services.values() if "serve" in " ".join(s.get("command", []))]
    workers = [s for s in services.values() if s.get("command") == ["fleethealth", "worker"]]
    assert len(apis) == 2
    for api in apis:
        assert api["environment"]["FLEETHEALTH_PROCESSOR_ENABLED"] == API_ENV["FLEETHEALTH_PROCESSOR_ENABLED"]
        assert api["environment"]["FLEETHEALTH_DATABASE_URL"].startswith("postgresql")
    assert sum(w.get("deploy", {}).get("replicas", 1) for w in workers) == 2
    assert all(w["environment"]["FLEETHEALTH_DATABASE_URL"].startswith("postgresql") for w in workers)
