"""A webhook receiver on 127.0.0.1 for tests: a threaded HTTP server that records each request
and can answer errors for a while (an outage), and the signature check a receiver makes."""

from __future__ import annotations

import hashlib
import hmac
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import orjson

TOLERANCE_S = 300


def verify(secret: str, headers: dict[str, str], body: bytes, now: float | None = None) -> bool:
    """The check docs/api.md gives receivers: the timestamp is recent and the signature is
    HMAC-SHA256(secret, "<timestamp>.<body>")."""
    ts = headers.get("x-fleethealth-timestamp", "")
    sig = headers.get("x-fleethealth-signature", "")
    if not ts.isdigit() or abs((now or time.time()) - int(ts)) > TOLERANCE_S:
        return False
    expected = "v1=" + hmac.new(secret.encode(), f"{ts}.".encode() + body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, sig)


@dataclass(frozen=True)
class Received:
    path: str
    headers: dict[str, str]
    body: bytes
    status: int

    @property
    def json(self) -> Any:
        return orjson.loads(self.body)


class Receiver:
    """Answers ``fail_first`` requests with 503 (or every one while ``down``), then 200, each
    after ``delay_s``."""

    def __init__(self, fail_first: int = 0, delay_s: float = 0.0) -> None:
        self.fail_first = fail_first
        self.delay_s = delay_s
        self.down = False
        self.received: list[Received] = []
        self._lock = threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (the stdlib's name)
                body = self.rfile.read(int(self.headers.get("content-length", "0")))
                if outer.delay_s:
                    time.sleep(outer.delay_s)
                with outer._lock:
                    failing = outer.down or len(outer.received) < outer.fail_first
                    status = 503 if failing else 200
                    outer.received.append(
                        Received(self.path, {k.lower(): v for k, v in self.headers.items()}, body, status)
                    )
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> Receiver:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.shutdown()
        self.server.server_close()

    def ok(self) -> list[Received]:
        with self._lock:
            return [r for r in self.received if r.status == 200]

    def wait_for(self, n_ok: int, timeout_s: float = 60.0) -> list[Received]:
        """Wait (bounded) until ``n_ok`` requests were answered 200."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            got = self.ok()
            if len(got) >= n_ok:
                return got
            time.sleep(0.05)
        raise AssertionError(f"{len(self.ok())} of {n_ok} deliveries arrived in {timeout_s} s: {self.received}")
