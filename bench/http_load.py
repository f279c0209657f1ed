"""A lean HTTP/1.1 load client for the message-rate benchmarks: prebuilt requests over kept-alive
connections (raw asyncio streams, uvloop when installed), in one or more client processes.

An ``httpx.AsyncClient`` spends about 2 ms of CPU per request: against a server that answers
``GET /healthz`` in 0.3 ms it is the client, not the server, that sets the rate. Here a request
is bytes built beforehand and an answer is its status line, its ``content-length`` and that many
body bytes, so one client process does several thousand requests per second on one core.

:func:`run_load` is the entry: each connection sends its own list of requests one after the
other (a request waits for the previous answer); connections are spread over ``processes``
client processes (``python bench/http_load.py``, the plan on stdin), which connect first, then
start together. Latencies are per request, from the first byte written to the last byte read;
the elapsed time runs from the common start to the last answer (``time.monotonic`` is one clock
for every process on Linux).
"""

from __future__ import annotations

import asyncio
import pickle
import resource
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field

#: An answer longer than this is not what these benchmarks expect (a few hundred bytes).
_MAX_HEAD_BYTES = 64 * 1024


@dataclass
class LoadResult:
    latencies_s: list[float] = field(default_factory=list)
    statuses: Counter[int] = field(default_factory=Counter)
    #: Requests sent again on a new connection: the server closed a kept-alive one before
    #: answering (every request here is idempotent: a batch id, a GET, or a 409 taken as done).
    resent: int = 0
    elapsed_s: float = 0.0
    #: CPU seconds the client processes used (user + system) from the start to the last answer.
    client_cpu_s: float = 0.0
    #: One answer body per status (the first seen), to show what went wrong.
    samples: dict[int, bytes] = field(default_factory=dict)


def request_bytes(
    method: str, path: str, host: str, body: bytes = b"", headers: dict[str, str] | None = None
) -> bytes:
    """One HTTP/1.1 keep-alive request, whole."""
    lines = [f"{method} {path} HTTP/1.1", f"host: {host}"]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    if body or method in ("POST", "PUT", "PATCH"):
        lines.append(f"content-length: {len(body)}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body


class ServerClosed(Exception):
    """The connection closed before a whole answer came."""


async def _answer(reader: asyncio.StreamReader) -> tuple[int, bytes, bool]:
    """``(status, body, keep_alive)`` of one answer (content-length framing only)."""
    try:
        head = await reader.readuntil(b"\r\n\r\n")
    except asyncio.IncompleteReadError as exc:
        raise ServerClosed() from exc
    except asyncio.LimitOverrunError as exc:
        raise ValueError("answer head too long") from exc
    status = int(head[9:12])
    length = 0
    keep_alive = True
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        name = name.strip().lower()
        if name == b"content-length":
            length = int(value)
        elif name == b"connection" and value.strip().lower() == b"close":
            keep_alive = False
        elif name == b"transfer-encoding":
            raise ValueError("chunked answers are not read by this client")
    try:
        body = await reader.readexactly(length) if length else b""
    except asyncio.IncompleteReadError as exc:
        raise ServerClosed() from exc
    return status, body, keep_alive


async def _connection(
    host: str, port: int, requests: list[bytes], result: LoadResult, connected: asyncio.Future[None],
    start: asyncio.Event,
) -> None:
    try:
        reader, writer = await asyncio.open_connection(host, port, limit=_MAX_HEAD_BYTES)
    except BaseException as exc:
        connected.set_exception(exc)
        raise
    connected.set_result(None)
    await start.wait()
    latencies = result.latencies_s
    perf = time.perf_counter
    try:
        for req in requests:
            for attempt in range(3):
                t0 = perf()
                writer.write(req)
                try:
                    status, body, keep_alive = await _answer(reader)
                    break
                except (ServerClosed, ConnectionError):
                    # Idle past the server's keep-alive timeout as the request went out.
                    if attempt == 2:
                        raise
                    result.resent += 1
                    writer.close()
                    reader, writer = await asyncio.open_connection(host, port, limit=_MAX_HEAD_BYTES)
            latencies.append(perf() - t0)
            result.statuses[status] += 1
            if status not in result.samples:
                result.samples[status] = body[:2000]
            if not keep_alive:
                writer.close()
                reader, writer = await asyncio.open_connection(host, port, limit=_MAX_HEAD_BYTES)
    finally:
        writer.close()


async def _run_plan(
    host: str, port: int, connections: list[list[bytes]], start: asyncio.Event
) -> tuple[list[asyncio.Future[None]], asyncio.Future[LoadResult]]:
    """Open every connection; returns their connected futures and the result, which comes once
    ``start`` is set and every request is answered."""
    loop = asyncio.get_running_loop()
    result = LoadResult()
    connected = [loop.create_future() for _ in connections]
    tasks = [
        asyncio.create_task(_connection(host, port, reqs, result, done, start))
        for reqs, done in zip(connections, connected, strict=True)
    ]

    async def finish() -> LoadResult:
        await start.wait()
        t0 = time.monotonic()
        await asyncio.gather(*tasks)
        result.elapsed_s = time.monotonic() - t0
        return result

    return connected, asyncio.ensure_future(finish())


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _event_loop_policy() -> None:
    try:
        import uvloop
    except ImportError:
        return
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())


def _child() -> int:
    """A client process: the plan on stdin, ``ready`` on stdout once connected, waits for a
    line on stdin, runs, writes the pickled result and its start time to stdout."""
    _event_loop_policy()
    host, port, connections = pickle.load(sys.stdin.buffer)

    async def main() -> tuple[float, LoadResult]:
        loop = asyncio.get_running_loop()
        go = asyncio.Event()
        connected, job = await _run_plan(host, port, connections, go)
        await asyncio.gather(*connected)
        sys.stdout.buffer.write(b"ready\n")
        sys.stdout.buffer.flush()
        await loop.run_in_executor(None, sys.stdin.buffer.readline)
        t0 = time.monotonic()
        cpu0 = _cpu_s()
        go.set()
        result = await job
        result.client_cpu_s = _cpu_s() - cpu0
        return t0, result

    t0, r = asyncio.run(main())
    # Plain values: this module is __main__ here, not where the parent finds LoadResult.
    sys.stdout.buffer.write(pickle.dumps((t0, r.latencies_s, dict(r.statuses), r.resent, r.elapsed_s, r.samples,
                                          r.client_cpu_s)))
    sys.stdout.buffer.flush()
    return 0


def run_load(host: str, port: int, connections: list[list[bytes]], processes: int = 1) -> LoadResult:
    """Send each connection's requests in order, all connections at once, over ``processes``
    client processes (the connections dealt round-robin); the merged result."""
    processes = max(1, min(processes, len(connections)))
    shares = [connections[i::processes] for i in range(processes)]
    children = [
        subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        for _ in shares
    ]
    try:
        for child, share in zip(children, shares, strict=True):
            assert child.stdin is not None
            child.stdin.write(pickle.dumps((host, port, share)))
            child.stdin.flush()
        for child in children:
            assert child.stdout is not None
            if child.stdout.readline() != b"ready\n":
                raise RuntimeError("a load client process failed to connect")
        for child in children:
            assert child.stdin is not None
            child.stdin.write(b"go\n")
            child.stdin.close()
        outs = []
        for child in children:
            assert child.stdout is not None
            t0, lat, statuses, resent, elapsed, samples, cpu = pickle.loads(child.stdout.read())
            outs.append((t0, LoadResult(lat, Counter(statuses), resent, elapsed, cpu, samples)))
            if child.wait(timeout=60) != 0:
                raise RuntimeError("a load client process failed")
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
    merged = LoadResult()
    t_start = min(t0 for t0, _ in outs)
    t_end = max(t0 + r.elapsed_s for t0, r in outs)
    for _, r in outs:
        merged.latencies_s += r.latencies_s
        merged.statuses.update(r.statuses)
        merged.resent += r.resent
        merged.client_cpu_s += r.client_cpu_s
        for status, body in r.samples.items():
            merged.samples.setdefault(status, body)
    merged.elapsed_s = t_end - t_start
    return merged


if __name__ == "__main__":
    raise SystemExit(_child())
