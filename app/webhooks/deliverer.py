"""The webhook deliverer: a thread of the server process that sends due outbox rows.

On PostgreSQL each round claims due rows with ``SELECT ... FOR UPDATE SKIP LOCKED`` and keeps
them locked while it sends them and records the outcome, in one transaction: several API
processes deliver side by side without sending a row twice at once, and a process that dies
mid-send releases its rows with its connection (the row is sent again: at least once, with the
same idempotency key). On SQLite (one process) a round reads the due rows, sends each, and
records each outcome in its own short write transaction, so ingest never waits behind a slow
receiver; a crash before the record leaves the row pending, to be sent again.
"""

from __future__ import annotations

import logging
import threading
import time

import httpx
from prometheus_client import Counter
from sqlalchemy.orm import Session

from app import __version__
from app.config import Settings
from app.db import Database
from app.models import utcnow
from app.webhooks import repository, service
from app.webhooks.repository import DueDelivery

log = logging.getLogger("fleethealth.webhooks")

ATTEMPTS = Counter("fleethealth_webhook_attempts_total", "Webhook delivery attempts", ["outcome"])


class Deliverer:
    def __init__(self, db: Database, settings: Settings) -> None:
        self.db = db
        self.settings = settings
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._client = httpx.Client(
            timeout=settings.webhook_timeout_s,
            follow_redirects=False,  # a redirect could leave the allowed targets
            headers={"user-agent": f"fleethealth-webhooks/{__version__}"},
        )

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleethealth-webhooks", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._client.close()

    def wake(self) -> None:
        """Deliver now rather than at the next poll (after a test-fire)."""
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sent = self.deliver_due()
            except Exception:
                log.exception("webhook delivery round failed")
                sent = 0
            if sent < self.settings.webhook_batch:
                self._wake.wait(self.settings.webhook_poll_s)
                self._wake.clear()

    # ------------------------------------------------------------------ one round
    def deliver_due(self) -> int:
        """Send the due deliveries (at most ``webhook_batch``); returns how many were tried."""
        limit = self.settings.webhook_batch
        if self.db.is_sqlite:
            with self.db.read() as s:
                due = repository.due(s, utcnow(), limit, lock=False)
            for d in due:
                if self._stop.is_set():
                    break
                outcome, final = self._attempt(d)
                with self.db.write() as s:
                    self._record(s, d, outcome, final)
            return len(due)
        with self.db.write() as s:
            due = repository.due(s, utcnow(), limit, lock=True)
            for d in due:
                outcome, final = self._attempt(d)
                self._record(s, d, outcome, final)
        return len(due)

    def _record(self, s: Session, d: DueDelivery, outcome: service.Outcome, final: bool) -> None:
        status = service.record_attempt(
            s,
            d.id,
            outcome,
            max_attempts=self.settings.webhook_max_attempts,
            base_s=self.settings.webhook_retry_base_s,
            max_s=self.settings.webhook_retry_max_s,
            final=final,
        )
        ATTEMPTS.labels("delivered" if outcome.ok else status).inc()

    def _attempt(self, d: DueDelivery) -> tuple[service.Outcome, bool]:
        """Send one delivery (after checking its URL is still allowed). The flag says the
        outcome is final (no retry can help)."""
        if not d.active:
            return service.Outcome(None, "subscription inactive", 0.0), True
        with self.db.read() as s:
            allowed = repository.target_prefixes(s, d.operator_id)
        if not service.url_allowed(d.url, allowed):
            return service.Outcome(
                None, "URL no longer within the allowed targets: not sent", 0.0
            ), True
        body = d.body.encode()
        ts = int(time.time())
        headers = {
            "content-type": "application/json",
            service.TIMESTAMP_HEADER: str(ts),
            service.SIGNATURE_HEADER: service.sign(d.secret, ts, body),
            "Idempotency-Key": d.idempotency_key,
            "X-Fleethealth-Event": d.event_type,
            "X-Fleethealth-Delivery": str(d.id),
            "X-Fleethealth-Attempt": str(d.attempts + 1),
        }
        t0 = time.perf_counter()
        try:
            r = self._client.post(d.url, content=body, headers=headers)
        except httpx.HTTPError as exc:
            ms = (time.perf_counter() - t0) * 1e3
            log.info("webhook delivery %s to %s failed: %s", d.id, d.url, exc)
            return service.Outcome(None, f"{type(exc).__name__}: {exc}", ms), False
        ms = (time.perf_counter() - t0) * 1e3
        error = None if 200 <= r.status_code < 300 else f"HTTP {r.status_code}"
        return service.Outcome(r.status_code, error, ms), False
