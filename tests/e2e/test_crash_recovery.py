"""Crash recovery: SIGKILL a real server mid-stream, restart it, finish; the stored outputs equal
those of an uninterrupted run."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fleethealth_client import FleetHealthClient

from tests.conftest import make_series
from tests.e2e.conftest import LiveServer

pytestmark = pytest.mark.e2e

FAKF = {"fakf": {"identification_samples": 500, "health_window_samples": 500}}
N_BATCHES = 24
BATCH = 500


def _feed(server: LiveServer, act: str, batches: range, series, wait_s: float = 0.0) -> None:  # type: ignore[no-untyped-def]
    with FleetHealthClient(server.url, server.api_key) as client:
        for k in batches:
            sl = slice(k * BATCH, (k + 1) * BATCH)
            client.post_batch(
                "E2E", act, f"b{k:03d}",
                {"current": series.current[sl], "voltage": series.voltage[sl]},
                t_s=series.t_s[sl], fmt="arrow", wait_s=wait_s,
            )


def _results(server: LiveServer, act: str) -> tuple[list, dict]:  # type: ignore[type-arg]
    base = f"{server.url}/v1/aircraft/E2E/actuators/{act}"
    hist = httpx.get(f"{base}/health/history?order=asc", headers=server.headers, timeout=30).json()["items"]
    out = httpx.get(f"{base}/outputs?estimator=fakf&max_samples=1000000&order=asc", headers=server.headers, timeout=30).json()
    return hist, out


def _wait_applied(server: LiveServer, act: str, seq: int, timeout_s: float = 60.0) -> dict:  # type: ignore[type-arg]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        h = httpx.get(f"{server.url}/v1/aircraft/E2E/actuators/{act}/health", headers=server.headers, timeout=10).json()
        if h["last_applied_seq"] >= seq:
            return h  # type: ignore[no-any-return]
        time.sleep(0.1)
    raise AssertionError(f"{act}: not applied up to {seq} within {timeout_s} s")


def test_sigkill_mid_stream_then_restart_gives_the_same_outputs(live_server: LiveServer, tmp_path: Path) -> None:
    server = live_server
    series = make_series(N_BATCHES * BATCH, seed=21)
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft("E2E")
        client.create_actuator("E2E", "reference", estimators=FAKF)
        client.create_actuator("E2E", "crashed", estimators=FAKF)

    # Uninterrupted reference run.
    _feed(server, "reference", range(N_BATCHES), series)
    _wait_applied(server, "reference", N_BATCHES)

    # Interrupted run: acknowledged batches pile up in the log, then the process dies mid-apply.
    _feed(server, "crashed", range(N_BATCHES // 2), series)
    server.kill()
    server.start()
    # Every acknowledged batch survived the crash...
    h = httpx.get(f"{server.url}/v1/aircraft/E2E/actuators/crashed/health", headers=server.headers).json()
    assert h["last_logged_seq"] == N_BATCHES // 2
    # ...a client retrying batches it is unsure of gets the first answers, and the rest follows.
    _feed(server, "crashed", range(N_BATCHES // 2 - 3, N_BATCHES), series)
    final = _wait_applied(server, "crashed", N_BATCHES)
    assert final["last_logged_seq"] == N_BATCHES

    ref_hist, ref_out = _results(server, "reference")
    got_hist, got_out = _results(server, "crashed")
    assert len(ref_hist) == len(got_hist) == N_BATCHES * BATCH // 500
    for a, b in zip(ref_hist, got_hist, strict=True):
        assert (a["t_start_s"], a["t_end_s"], a["status"], a["indicators"]) == (
            b["t_start_s"], b["t_end_s"], b["status"], b["indicators"])
    assert ref_out["t_s"] == got_out["t_s"]
    for name in ref_out["series"]:
        np.testing.assert_array_equal(
            np.array(ref_out["series"][name], dtype=float), np.array(got_out["series"][name], dtype=float))


def reference_and_target(server: LiveServer, seed: int):  # type: ignore[no-untyped-def]
    """Actuators ``ref`` (fed all of a series and applied, uninterrupted) and ``k`` (empty);
    the series."""
    series = make_series(N_BATCHES * BATCH, seed=seed)
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft("E2E")
        client.create_actuator("E2E", "ref", estimators=FAKF)
        client.create_actuator("E2E", "k", estimators=FAKF)
    _feed(server, "ref", range(N_BATCHES), series)
    _wait_applied(server, "ref", N_BATCHES)
    return series


def test_kill_during_apply_repeatedly(live_server: LiveServer) -> None:
    """Kill the server several times while it is applying; no batch is lost or applied twice."""
    server = live_server
    series = reference_and_target(server, seed=22)
    step = N_BATCHES // 4
    for part in range(4):
        _feed(server, "k", range(part * step, (part + 1) * step), series)
        time.sleep(0.05 * part)  # vary where in the apply the kill lands
        server.kill()
        server.start()
    _wait_applied(server, "k", N_BATCHES)
    ref_hist, ref_out = _results(server, "ref")
    got_hist, got_out = _results(server, "k")
    assert [w["indicators"] for w in ref_hist] == [w["indicators"] for w in got_hist]
    assert ref_out == {**got_out}
