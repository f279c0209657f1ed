"""SQLite's apply process (``APPLY_PROCESS=on``, the default): a real ``fleethealth serve`` on
loopback applies its streams in a child process. The child is SIGKILLed mid-stream, several
times; ``serve`` starts another, nothing is lost or applied twice, waiters and fleet-event
subscribers of ``serve`` hear of the applies, and ``/metrics`` counts the child's work."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest
from fleethealth_client import FleetHealthClient

from tests.conftest import make_series
from tests.e2e.conftest import LiveServer
from tests.e2e.test_crash_recovery import (
    BATCH,
    FAKF,
    N_BATCHES,
    _feed,
    _results,
    _wait_applied,
    reference_and_target,
)
from tests.e2e.test_workers import FleetSubscriber

pytestmark = pytest.mark.e2e

CHILD_MARK = b"app.processing.apply_process"


def apply_children(server: LiveServer) -> list[int]:
    """Pids of the server's live apply processes (from /proc)."""
    assert server.proc is not None
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, IndexError):
            continue
        if ppid == server.proc.pid and CHILD_MARK in cmdline:
            found.append(int(entry.name))
    return found


def wait_new_child(server: LiveServer, old: int, timeout_s: float = 60.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pids = [p for p in apply_children(server) if p != old]
        if pids:
            return pids[0]
        time.sleep(0.1)
    raise AssertionError(f"no apply process replaced {old} within {timeout_s} s")


def metric(server: LiveServer, name: str) -> dict[str, float]:
    """Samples of one metric by their label text."""
    text = httpx.get(f"{server.url}/metrics", headers=server.headers, timeout=10).text
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line.startswith(name + "{") or line.startswith(name + " "):
            key, _, value = line.rpartition(" ")
            out[key[len(name):]] = float(value)
    return out


def test_the_processor_runs_in_a_child_and_serve_reports_its_work(live_server: LiveServer) -> None:
    server = live_server
    (child,) = apply_children(server)
    series = make_series(4 * BATCH, seed=41)
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft("E2E")
        client.create_actuator("E2E", "a", estimators=FAKF)
    applied_before = metric(server, "fleethealth_batches_applied_total").get("", 0.0)
    with FleetSubscriber(server) as sub:
        _feed(server, "a", range(4), series, wait_s=60.0)
        # ?wait= answered after the child's apply committed: applied by the time it returns.
        h = httpx.get(f"{server.url}/v1/aircraft/E2E/actuators/a/health", headers=server.headers, timeout=10).json()
        assert h["last_applied_seq"] == 4
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(sub.applied_seqs("a")) < 4:
            time.sleep(0.05)
    # The fleet events of serve's subscribers come from the child's announcements.
    assert sorted(sub.applied_seqs("a")) == [1, 2, 3, 4]
    # The child reports its metrics every second.
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and metric(server, "fleethealth_batches_applied_total")[""] < applied_before + 4:
        time.sleep(0.2)
    assert metric(server, "fleethealth_batches_applied_total")[""] >= applied_before + 4
    threads = metric(server, "fleethealth_thread_cpu_seconds_total")
    assert any('thread="apply:fleethealth-processor"' in k for k in threads), threads
    assert not any('thread="fleethealth-processor"' in k for k in threads), threads  # none in serve
    assert apply_children(server) == [child]


def test_sigterm_to_serve_alone_ends_its_apply_process(live_server: LiveServer) -> None:
    """A SIGTERM to ``serve`` only (not its process group, as a service manager or ``kill``
    sends it): ``serve`` closes its end of the socket and the child, seeing it end, finishes
    and exits by itself, before the shutdown timeout (``serve`` would kill it then, and say
    so in its log). The reader thread's file object must not keep the socket open."""
    server = live_server
    assert server.proc is not None
    (child,) = apply_children(server)
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft("E2E")
        client.create_actuator("E2E", "a", estimators=FAKF)
    _feed(server, "a", range(1), make_series(BATCH, seed=43), wait_s=60.0)
    server.proc.send_signal(signal.SIGTERM)
    server.proc.wait(30)
    log = server.log_path.read_text(errors="replace")
    assert "did not exit within" not in log, log[-2000:]
    assert not Path(f"/proc/{child}").exists() or b"zombie" in Path(f"/proc/{child}/status").read_bytes().lower()


def test_sigkill_the_apply_process_mid_stream(live_server: LiveServer) -> None:
    server = live_server
    series = reference_and_target(server, seed=42)

    step = N_BATCHES // 4
    with FleetSubscriber(server) as sub:
        for part in range(3):
            (child,) = apply_children(server)
            _feed(server, "k", range(part * step, (part + 1) * step), series)
            time.sleep(0.05 * part)  # vary where in the apply the kill lands
            os.kill(child, signal.SIGKILL)
            wait_new_child(server, child)
        # After the last kill: ?wait= is answered by the new child's announcement.
        _feed(server, "k", range(3 * step, N_BATCHES), series, wait_s=60.0)
        final = _wait_applied(server, "k", N_BATCHES)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and N_BATCHES not in sub.applied_seqs("k"):
            time.sleep(0.05)

    assert final["last_logged_seq"] == final["last_applied_seq"] == N_BATCHES  # nothing lost
    ref_hist, ref_out = _results(server, "ref")
    got_hist, got_out = _results(server, "k")
    # Applied exactly once, in order: the outputs of the uninterrupted run.
    assert [(w["t_start_s"], w["indicators"], w["status"]) for w in got_hist] == [
        (w["t_start_s"], w["indicators"], w["status"]) for w in ref_hist]
    assert got_out == ref_out
    seqs = sub.applied_seqs("k")
    assert len(seqs) == len(set(seqs)), seqs  # no batch announced twice
    # An announcement is sent after its commit; a child killed between the two loses it (the
    # waiters re-read when the next child starts), so only the batches logged after the last
    # kill are sure to be heard of.
    assert set(range(3 * step + 1, N_BATCHES + 1)) <= set(seqs), seqs
