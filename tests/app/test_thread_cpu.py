"""``fleethealth_thread_cpu_seconds_total``: CPU of the process's threads by name."""

from __future__ import annotations

import sys
import threading
import time

import pytest

from app.system.threads import thread_cpu_seconds

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/task")


def test_a_busy_threads_cpu_is_counted_under_its_pool_name() -> None:
    burned = [threading.Event(), threading.Event()]
    release = threading.Event()

    def burn(k: int) -> None:
        t_end = time.thread_time() + 0.2
        spins = 0
        while time.thread_time() < t_end:  # 0.2 s of this thread's own CPU
            spins += 1
        assert spins > 0
        burned[k].set()
        release.wait(30)  # alive while it is read

    threads = [threading.Thread(target=burn, args=(k,), name=f"test-burner_{k}") for k in range(2)]
    for t in threads:
        t.start()
    try:
        assert all(e.wait(30) for e in burned)
        cpu = thread_cpu_seconds()
        assert "test-burner" in cpu and not any(k.startswith("test-burner_") for k in cpu)
        assert cpu["test-burner"] >= 0.35  # 2 x 0.2 s, less a clock tick (10 ms) each
        assert cpu["MainThread"] > 0.0
    finally:
        release.set()
        for t in threads:
            t.join(30)


def test_the_metric_is_served(api) -> None:  # type: ignore[no-untyped-def]
    body = api.get("/metrics").text
    assert 'fleethealth_thread_cpu_seconds_total{thread="MainThread"}' in body
