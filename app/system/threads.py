"""CPU time of this process's threads, by thread name, for ``/metrics``.

``fleethealth_thread_cpu_seconds_total{thread=...}``: user + system CPU seconds of the live
threads of each name (a pool's threads, numbered ``name_0``, ``name_1``..., are counted under
their common name), read from ``/proc/self/task/<id>/stat`` on each scrape (Linux; nothing
elsewhere). It shows which part of the service is busy: the event loop (``MainThread``), the
request pool (``AnyIO worker thread``), the log writer, the processor, the WebSocket parse pool.
A thread that ended takes its CPU out of the sum, so read it as a gauge over short spans.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily
from prometheus_client.registry import REGISTRY, Collector

_POOL_INDEX = re.compile(r"_\d+$")
_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def thread_cpu_seconds() -> dict[str, float]:
    """User + system CPU seconds of the live threads, summed by name (pool indices dropped)."""
    out: dict[str, float] = {}
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None:
            continue
        try:
            with open(f"/proc/self/task/{tid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
        except OSError:  # not Linux, or the thread just ended
            continue
        name = _POOL_INDEX.sub("", t.name)
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / _TICKS
    return out


class ThreadCpuCollector(Collector):
    def collect(self) -> Iterator[CounterMetricFamily]:
        family = CounterMetricFamily(
            "fleethealth_thread_cpu_seconds", "CPU seconds (user + system) of this process's live threads, by name",
            labels=["thread"],
        )
        for name, seconds in sorted(thread_cpu_seconds().items()):
            family.add_metric([name], seconds)
        yield family


_registered = False


def register() -> None:
    """Add the collector to the default registry (once per process)."""
    global _registered
    if not _registered:
        REGISTRY.register(ThreadCpuCollector())
        _registered = True
