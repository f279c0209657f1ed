"""Waiting for a server to accept telemetry and for its estimator kernels, with a progress line.

A server answers, and logs batches durably, while it compiles its estimator kernels kind by kind
(minutes on a fresh install, about a second afterwards); each kind's streams are applied once that
kind is ready. ``/readyz`` tells both: ``checks.database`` and ``checks.schema`` at ``ok`` mean
batches are accepted, ``kernels`` gives each kind's status.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Collection
from typing import Any

from fleethealth_client import FleetHealthClient

Log = Callable[[str], Any]

#: Seconds between two progress lines.
PROGRESS_EVERY_S = 15.0
#: Seconds before the first progress line.
FIRST_PROGRESS_S = 5.0
#: Seconds between two polls of ``/readyz``.
POLL_S = 0.5
#: Kernel statuses after which nothing more happens (a failed kind's streams are applied anyway).
SETTLED = ("ready", "failed")


def readiness(client: FleetHealthClient) -> dict[str, Any] | None:
    """The ``/readyz`` body, or None while the server does not answer."""
    with contextlib.suppress(Exception):  # refused, timeout, not our server yet: "not yet"
        return client.readiness()
    return None


def accepts_telemetry(body: dict[str, Any] | None) -> bool:
    checks = (body or {}).get("checks") or {}
    return checks.get("database") == "ok" and checks.get("schema") == "ok"


def kinds_settled(body: dict[str, Any] | None, kinds: Collection[str] | None) -> bool:
    """Whether every kind in ``kinds`` (every kind the server has, for None) is ready or failed."""
    kernels: dict[str, Any] = (body or {}).get("kernels") or {}
    wanted = kernels.keys() if kinds is None else kinds
    return bool(kernels) and all(
        (kernels.get(kind) or {}).get("status") in SETTLED for kind in wanted
    )


def describe(body: dict[str, Any] | None, kinds: Collection[str] | None = None) -> str:
    """One line: ``fakf ready (9 s), stmmae compiling (41 s), ...``."""
    if body is None:
        return "server not answering yet"
    if not accepts_telemetry(body):
        checks = body.get("checks") or {}
        return "; ".join(f"{name}: {value}" for name, value in checks.items() if value != "ok")
    parts = []
    for kind, k in (body.get("kernels") or {}).items():
        if kinds is not None and kind not in kinds:
            continue
        seconds = f" ({k['seconds']:.0f} s)" if "seconds" in k else ""
        error = f": {k['error']}" if k.get("error") else ""
        parts.append(f"{kind} {k.get('status')}{seconds}{error}")
    return ", ".join(parts) or "no kernels reported"


def wait_for_server(
    client: FleetHealthClient,
    *,
    kinds: Collection[str] | None = (),
    timeout_s: float | None = None,
    stop_event: threading.Event | None = None,
    log: Log = print,
    prefix: str = "",
    progress_every_s: float = PROGRESS_EVERY_S,
) -> dict[str, Any] | None:
    """Wait until the server accepts telemetry and the kernels of ``kinds`` are ready or failed.

    Args:
        client: the server's client.
        kinds: estimator kinds to wait for; ``()`` waits for nothing beyond telemetry being
            accepted, None for every kind the server has.
        timeout_s: give up after this long; None waits however long it takes.
        stop_event: stops the wait when set.
        log: receives a progress line every ``progress_every_s`` seconds while waiting.
        prefix: put before each line (``"simulate: "``).

    Returns:
        the last ``/readyz`` body once the wait is over, None if it timed out or was stopped.
    """
    started = time.monotonic()
    next_progress = started + min(progress_every_s, FIRST_PROGRESS_S)
    while True:
        body = readiness(client)
        if accepts_telemetry(body) and (kinds == () or kinds_settled(body, kinds)):
            if time.monotonic() - started > progress_every_s:
                log(f"{prefix}server ready after {time.monotonic() - started:.0f} s: {describe(body, kinds)}")
            return body
        now = time.monotonic()
        if timeout_s is not None and now - started >= timeout_s:
            log(f"{prefix}server not ready after {timeout_s:g} s: {describe(body, kinds)}")
            return None
        if now >= next_progress:
            log(f"{prefix}waiting for the server ({now - started:.0f} s): {describe(body, kinds)}")
            next_progress = now + progress_every_s
        if stop_event is not None:
            if stop_event.wait(POLL_S):
                return None
        else:
            time.sleep(POLL_S)


class KernelProgress:
    """Progress lines while a server's kernels get ready, checked from a sending loop.

    ``check()`` polls ``/readyz`` at most every ``progress_every_s`` seconds and logs one line
    until every kind in ``kinds`` is ready or failed, then one last line.
    """

    def __init__(
        self,
        client: FleetHealthClient,
        kinds: Collection[str] | None,
        *,
        log: Log = print,
        prefix: str = "",
        progress_every_s: float = PROGRESS_EVERY_S,
    ) -> None:
        self.client = client
        self.kinds = kinds
        self.log = log
        self.prefix = prefix
        self.every_s = progress_every_s
        self.started = time.monotonic()
        # The first line after a few seconds: a server with a warm cache is ready by then.
        self._next = self.started + FIRST_PROGRESS_S
        self.settled = False

    def check(self) -> None:
        if self.settled or time.monotonic() < self._next:
            return
        self._next = time.monotonic() + self.every_s
        body = readiness(self.client)
        elapsed = time.monotonic() - self.started
        if kinds_settled(body, self.kinds):
            self.settled = True
            self.log(f"{self.prefix}kernels ready ({describe(body, self.kinds)})")
            return
        self.log(
            f"{self.prefix}kernels compiling ({elapsed:.0f} s): {describe(body, self.kinds)}; "
            "batches are logged meanwhile and applied once their kind is ready"
        )
