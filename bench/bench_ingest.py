"""End-to-end ingest benchmark against a real ``fleethealth serve`` process on 127.0.0.1.

What is measured (samples = time stamps; each carries two channels, ``current`` and ``voltage``):

* one stream: batches of 10,000 samples sent one after the other, per format (JSON, CSV, Arrow);
  the clock runs from the first request until the server reports the last batch applied by the
  FAKF with its results committed (``last_applied_seq``);
* 100 streams at once: the same, each stream sending its batches in order, streams concurrently
  through the asyncio client with bounded concurrency; the clock stops when every stream's last
  batch is applied (polled through ``/v1/fleet/health``);
* memory per registered stream: resident memory of the server process tree (``/proc``) before and
  after registering N actuators and feeding each one small batch, divided by N. This runs first, on
  a fresh server warmed by one stream, so that the throughput runs do not pre-grow the heap.

The voltage is the paper's current-to-voltage ARX model (-40 lbs identification) driven by a
multi-sine current, plus noise, so the FAKF identifies and filters as on real data.

Usage::

    .venv/bin/python bench/bench_ingest.py                 # SQLite in a temporary folder
    .venv/bin/python bench/bench_ingest.py --quick         # smaller, for a smoke run
    .venv/bin/python bench/bench_ingest.py --pg postgresql+psycopg://user:pw@127.0.0.1/db

Figures are printed (and written as JSON with ``--json-out``); nothing is asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import http_load  # noqa: E402
from fleethealth_client import (  # noqa: E402
    AsyncFleetHealthClient,
    EncodedBatch,
    FleetHealthClient,
    encode_batch,
)

FORMATS = ("json", "csv", "arrow")
GOALS_SAMPLES_S = {"arrow": 1_000_000, "json": 300_000}
GOAL_BYTES_PER_IDLE_STREAM = 2048
PROG_SERVER_SAMPLES_S = "40-170"
SAMPLE_RATE_HZ = 1000.0
# How often the many-stream case looks whether every stream is applied (about 5 % of a 4-8 s run).
FLEET_POLL_S = 0.1
# Seed paper, Table 1, -40 lbs: V[k] = -a0 V[k-1] - a1 V[k-2] + b0 I[k] + b1 I[k-1] + b2 I[k-2].
ARX_A = (1.0, -0.4998, -0.0343)
ARX_B = (-0.7889, 5.9267, -3.5857)


@dataclass
class Row:
    backend: str
    case: str
    fmt: str
    streams: int
    samples: int
    ack_s: float
    applied_s: float
    encode_s: float = float("nan")
    # CPU seconds the server process used during the case (user + system, all its threads).
    server_cpu_s: float = float("nan")

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.applied_s if self.applied_s > 0 else float("nan")

    @property
    def server_cpu_us_per_sample(self) -> float:
        """Server CPU per sample: on a loaded shared machine far steadier than the rate."""
        return 1e6 * self.server_cpu_s / self.samples if self.samples else float("nan")


# ------------------------------------------------------------------------------------------------
# Server process
# ------------------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def fleethealth_exe() -> str:
    exe = Path(sys.executable).parent / "fleethealth"
    if exe.exists():
        return str(exe)
    found = shutil.which("fleethealth")
    if found is None:
        raise SystemExit("the fleethealth command is not installed (pip install -e .)")
    return found


@dataclass
class Server:
    url: str
    api_key: str
    process: subprocess.Popen[bytes]
    log_path: Path


def fleethealth_command(source: Path | None) -> list[str]:
    """The ``fleethealth`` command, of this checkout or of another source tree (``source``:
    its ``app`` package is imported first, e.g. ``git worktree add /tmp/base main``)."""
    if source is None:
        return [fleethealth_exe()]
    return [sys.executable, "-m", "app.cli"]


@contextmanager
def running_server(
    database_url: str,
    workdir: Path,
    ready_timeout_s: float,
    source: Path | None = None,
    extra_env: dict[str, str] | None = None,
) -> Iterator[Server]:
    """Migrate the database, start ``fleethealth serve`` and stop it (and only it) at the end."""
    api_key = secrets.token_urlsafe(24)
    env = dict(os.environ)
    env.update(
        {
            "FLEETHEALTH_DATABASE_URL": database_url,
            "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": api_key,
            **(extra_env or {}),
        }
    )
    if source is not None:
        env["PYTHONPATH"] = f"{source}{os.pathsep}{source / 'clients' / 'python'}"
    cmd = fleethealth_command(source)
    migrate = subprocess.run(
        [*cmd, "migrate"], env=env, cwd=workdir, capture_output=True, text=True, timeout=300
    )
    if migrate.returncode != 0:
        raise SystemExit(f"fleethealth migrate failed:\n{migrate.stdout}\n{migrate.stderr}")
    port = free_port()
    log_path = workdir / f"server-{port}.log"
    log_file = open(log_path, "wb")  # noqa: SIM115 - closed in finally
    process = subprocess.Popen(
        [*cmd, "serve", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
        env=env,
        cwd=workdir,
        stdout=log_file,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    server = Server(f"http://127.0.0.1:{port}", api_key, process, log_path)
    try:
        _wait_ready(server, ready_timeout_s)
        yield server
    finally:
        _stop(process)
        log_file.close()


def _wait_ready(server: Server, timeout_s: float) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.process.poll() is not None:
            break
        with contextlib.suppress(httpx.TransportError):  # not listening yet
            if httpx.get(server.url + "/readyz", timeout=2.0).status_code == 200:
                return
        time.sleep(0.2)
    tail = server.log_path.read_text(errors="replace")[-4000:]
    raise SystemExit(f"server not ready within {timeout_s:g} s; log:\n{tail}")


def _stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=10)


def _tree(pid: int) -> list[int]:
    """A process and its live descendants (the apply process of ``APPLY_PROCESS=on``), from /proc."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry))
    found, stack = [], [pid]
    while stack:
        current = stack.pop()
        found.append(current)
        stack.extend(children.get(current, []))
    return found


def tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) used so far by a process, its threads and its live child
    processes, from /proc: on a machine shared with other work, CPU per request is steadier
    than wall-clock rates."""
    total = 0
    for current in _tree(pid):
        with contextlib.suppress(OSError):  # the process ended meanwhile
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def tree_rss_bytes(pid: int) -> int:
    """Resident memory of a process and its descendants, from /proc."""
    total = 0
    for current in _tree(pid):
        with contextlib.suppress(OSError):  # the process ended meanwhile
            for line in Path(f"/proc/{current}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
    return total


# ------------------------------------------------------------------------------------------------
# Data
# ------------------------------------------------------------------------------------------------


def make_stream(n: int, seed: int, t0: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    t_s = t0 + np.arange(n, dtype=np.float64) / SAMPLE_RATE_HZ
    tt = t_s - t0
    current = (
        1.5 * np.sin(2 * np.pi * 0.5 * tt + rng.uniform(0, 6.3))
        + 0.6 * np.sin(2 * np.pi * 3.1 * tt)
        + 0.3 * np.sin(2 * np.pi * 11.0 * tt)
        + rng.normal(0.0, 0.05, n)
    )
    voltage = lfilter(ARX_B, ARX_A, current) + rng.normal(0.0, 1.0, n)
    return t_s, {"current": current, "voltage": voltage}


def encode_stream(
    fmt: str,
    prefix: str,
    t_s: np.ndarray,
    channels: dict[str, np.ndarray],
    batch_samples: int,
) -> list[tuple[str, EncodedBatch, int]]:
    out = []
    for b in range(len(t_s) // batch_samples):
        sl = slice(b * batch_samples, (b + 1) * batch_samples)
        batch_id = f"{prefix}-{b:05d}"
        encoded = encode_batch(fmt, batch_id, {k: v[sl] for k, v in channels.items()}, t_s=t_s[sl])
        out.append((batch_id, encoded, batch_samples))
    return out


# ------------------------------------------------------------------------------------------------
# Cases
# ------------------------------------------------------------------------------------------------


def bench_single(
    client: FleetHealthClient,
    backend: str,
    tail: str,
    fmt: str,
    n_batches: int,
    batch_samples: int,
    timeout_s: float,
) -> Row:
    actuator_id = f"single-{fmt}"
    client.create_actuator(tail, actuator_id, channels=["current", "voltage"])
    t_s, channels = make_stream(n_batches * batch_samples, seed=1, t0=1.7e9)
    encode_start = time.perf_counter()
    batches = encode_stream(fmt, actuator_id, t_s, channels, batch_samples)
    encode_s = time.perf_counter() - encode_start
    start = time.perf_counter()
    seq = -1
    for _, encoded, _ in batches:
        seq = int(client.post_encoded(tail, actuator_id, encoded)["seq"])
    ack_s = time.perf_counter() - start
    client.wait_applied(tail, actuator_id, seq, timeout_s=timeout_s, poll_s=0.01)
    applied_s = time.perf_counter() - start
    samples = n_batches * batch_samples
    return Row(backend, "1 stream", fmt, 1, samples, ack_s, applied_s, encode_s)


async def _bench_many_async(
    server: Server,
    tail: str,
    fmt: str,
    streams: int,
    n_batches: int,
    batch_samples: int,
    concurrency: int,
    timeout_s: float,
) -> tuple[float, float, float]:
    async with AsyncFleetHealthClient(
        server.url, server.api_key, timeout=120.0, max_connections=concurrency
    ) as client:
        actuator_ids = [f"many-{fmt}-{i:03d}" for i in range(streams)]
        registration = asyncio.Semaphore(concurrency)

        async def register(actuator_id: str) -> None:
            async with registration:
                await client.create_actuator(tail, actuator_id, channels=["current", "voltage"])

        await asyncio.gather(*(register(a) for a in actuator_ids))
        encoded = {
            a: encode_stream(
                fmt, a, *make_stream(n_batches * batch_samples, 100 + i, 1.7e9), batch_samples
            )
            for i, a in enumerate(actuator_ids)
        }
        last_seq: dict[str, int] = {}
        sending = asyncio.Semaphore(concurrency)

        async def send(actuator_id: str) -> None:
            for _, body, _ in encoded[actuator_id]:
                async with sending:
                    ack = await client.post_encoded(tail, actuator_id, body)
                last_seq[actuator_id] = int(ack["seq"])

        # The server's CPU from here on (registering the actuators is not the batches' cost).
        cpu_start = tree_cpu_s(server.process.pid)
        start = time.perf_counter()
        await asyncio.gather(*(send(a) for a in actuator_ids))
        ack_s = time.perf_counter() - start
        deadline = time.monotonic() + timeout_s
        while True:
            fleet = await client.fleet_health(sort="tail")
            applied = {
                act["actuator_id"]: act.get("last_applied_seq")
                for aircraft in fleet["aircraft"]
                if aircraft["tail"] == tail
                for act in aircraft["actuators"]
            }
            if all(applied.get(a) is not None and applied[a] >= seq for a, seq in last_seq.items()):
                break
            if time.monotonic() > deadline:
                raise TimeoutError(f"{fmt}: streams not applied within {timeout_s:g} s")
            # Each look reads the whole fleet board: every 20 ms it took about 6 % of the
            # server's CPU (py-spy) away from the batches being measured.
            await asyncio.sleep(FLEET_POLL_S)
        applied_s = time.perf_counter() - start
        return ack_s, applied_s, tree_cpu_s(server.process.pid) - cpu_start


def bench_many(
    server: Server,
    backend: str,
    tail: str,
    fmt: str,
    streams: int,
    n_batches: int,
    batch_samples: int,
    concurrency: int,
    timeout_s: float,
) -> Row:
    ack_s, applied_s, cpu_s = asyncio.run(
        _bench_many_async(
            server, tail, fmt, streams, n_batches, batch_samples, concurrency, timeout_s
        )
    )
    samples = streams * n_batches * batch_samples
    row = Row(backend, f"{streams} streams", fmt, streams, samples, ack_s, applied_s)
    row.server_cpu_s = cpu_s
    return row


# ------------------------------------------------------------------------------------------------
# Message rate: one sample per POST, plain writes
# ------------------------------------------------------------------------------------------------


def _one_sample(k: int) -> bytes:
    body = {"batch_id": f"m{k}", "t": [1.7e9 + k * 0.01], "channels": {"current": [0.3], "voltage": [-8.0]}}
    return json.dumps(body, separators=(",", ":")).encode()


def _lat_figures(lat: list[float], elapsed_s: float) -> dict[str, float]:
    arr = np.asarray(lat)
    return {
        "requests": float(arr.size),
        "per_s": arr.size / elapsed_s,
        "median_ms": float(np.median(arr) * 1e3),
        "p99_ms": float(np.percentile(arr, 99) * 1e3),
    }


def _load(server: Server, connections: list[list[bytes]], expect: set[int], processes: int = 1) -> dict[str, float]:
    """Run prebuilt requests through the lean client (:mod:`http_load`); the latency figures,
    and how many requests were resent on a new connection."""
    host, port = server.url.removeprefix("http://").split(":")
    result = http_load.run_load(host, int(port), connections, processes)
    wrong = {status: n for status, n in result.statuses.items() if status not in expect}
    if wrong:
        status = next(iter(wrong))
        raise SystemExit(f"answered {wrong} (expected {sorted(expect)}): {result.samples[status][:500]!r}")
    return _lat_figures(result.latencies_s, result.elapsed_s) | {
        "resent": float(result.resent), "client_cpu_ms": 1e3 * result.client_cpu_s / len(result.latencies_s)
    }


def _post(server: Server, path: str, body: bytes) -> bytes:
    host = server.url.removeprefix("http://")
    headers = {"authorization": f"Bearer {server.api_key}", "content-type": "application/json"}
    return http_load.request_bytes("POST", path, host, body, headers)


def bench_post1_sequential(server: Server, tail: str, n: int, timeout_s: float) -> dict[str, float]:
    """One client, one sample per POST, one request after the other (latency)."""
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_actuator(tail, "seq", kind="ema_voltage")
        path = f"/v1/aircraft/{tail}/actuators/seq/telemetry"
        start = time.perf_counter()
        figures = _load(server, [[_post(server, path, _one_sample(k)) for k in range(n)]], {202})
        client.wait_applied(tail, "seq", n, timeout_s=timeout_s, poll_s=0.01)
        figures["applied_s"] = time.perf_counter() - start
    return figures


def bench_post1_concurrent(
    server: Server, tail: str, clients: int, per_client: int, processes: int, timeout_s: float
) -> dict[str, float]:
    """``clients`` concurrent clients (connections, over ``processes`` client processes), each
    its own stream, one sample per POST; then waits until every sample is applied (so that the
    server CPU of this case includes their apply, and the next case starts without a backlog)."""
    with FleetHealthClient(server.url, server.api_key) as client:
        for i in range(clients):
            client.create_actuator(tail, f"c{i:03d}", kind="ema_voltage")
        connections = [
            [_post(server, f"/v1/aircraft/{tail}/actuators/c{i:03d}/telemetry", _one_sample(k))
             for k in range(per_client)]
            for i in range(clients)
        ]
        start = time.perf_counter()
        figures = _load(server, connections, {202}, processes)
        for i in range(clients):
            client.wait_applied(tail, f"c{i:03d}", per_client, timeout_s=timeout_s, poll_s=0.05)
        figures["applied_s"] = time.perf_counter() - start
    return figures


def bench_plain_write(server: Server, tail_prefix: str, n: int) -> dict[str, float]:
    """POST /v1/aircraft one after the other: a write with no telemetry log behind it."""
    requests = [_post(server, "/v1/aircraft", json.dumps({"tail": f"{tail_prefix}{k:05d}"}).encode())
                for k in range(n)]
    return _load(server, [requests], {201})


def bench_fdatasync(folder: Path, n: int = 200) -> dict[str, float]:
    """4 KiB written and ``fdatasync`` -ed, ``n`` times, in the database's folder: the floor of a
    durable acknowledgement's latency on this disk (SQLite ``synchronous=FULL`` syncs its WAL
    once per commit)."""
    path = folder / f"fdatasync-probe-{secrets.token_hex(4)}"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    lat: list[float] = []
    try:
        block = b"\0" * 4096
        start = time.perf_counter()
        for _ in range(n):
            t0 = time.perf_counter()
            os.write(fd, block)
            os.fdatasync(fd)
            lat.append(time.perf_counter() - t0)
        return _lat_figures(lat, time.perf_counter() - start)
    finally:
        os.close(fd)
        path.unlink()


def bench_floor(server: Server, clients: int, n: int, processes: int) -> dict[str, float]:
    """GET /healthz (no key, no database, no thread) from ``clients`` concurrent clients: what
    the HTTP stack alone (uvicorn, the application's routing and middleware) costs, the ceiling
    of any other route."""
    request = http_load.request_bytes("GET", "/healthz", server.url.removeprefix("http://"))
    return _load(server, [[request] * n for _ in range(clients)], {200}, processes)


async def _register_idle(
    server: Server, tail: str, n: int, batch_samples: int, concurrency: int, timeout_s: float
) -> None:
    async with AsyncFleetHealthClient(
        server.url, server.api_key, timeout=120.0, max_connections=concurrency
    ) as client:
        gate = asyncio.Semaphore(concurrency)
        last_seq: dict[str, int] = {}

        async def one(i: int) -> None:
            actuator_id = f"idle-{i:05d}"
            t_s, channels = make_stream(batch_samples, seed=10_000 + i, t0=1.7e9)
            async with gate:
                await client.create_actuator(tail, actuator_id, channels=["current", "voltage"])
                ack = await client.post_batch(
                    tail, actuator_id, f"idle-{i}", channels, t_s=t_s, fmt="arrow"
                )
            last_seq[actuator_id] = int(ack["seq"])

        await asyncio.gather(*(one(i) for i in range(n)))
        deadline = time.monotonic() + timeout_s
        while True:
            fleet = await client.fleet_health(sort="tail")
            applied = {
                act["actuator_id"]: act.get("last_applied_seq")
                for aircraft in fleet["aircraft"]
                if aircraft["tail"] == tail
                for act in aircraft["actuators"]
            }
            if all(applied.get(a) is not None and applied[a] >= s for a, s in last_seq.items()):
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"idle streams not applied within {timeout_s:g} s")
            await asyncio.sleep(0.1)


def bench_memory(
    server: Server, tail: str, n: int, batch_samples: int, concurrency: int, timeout_s: float
) -> tuple[int, int, float]:
    time.sleep(1.0)
    before = tree_rss_bytes(server.process.pid)
    asyncio.run(_register_idle(server, tail, n, batch_samples, concurrency, timeout_s))
    time.sleep(1.0)
    after = tree_rss_bytes(server.process.pid)
    return before, after, (after - before) / n


# ------------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------------


def run_backend(
    backend: str, database_url: str, workdir: Path, args: argparse.Namespace, source: Path | None = None,
    extra_env: dict[str, str] | None = None,
) -> dict:
    rows: list[Row] = []
    memory: dict[str, float] = {}
    rate: dict[str, dict[str, float]] = {}
    run_id = secrets.token_hex(3).upper()
    with running_server(database_url, workdir, args.ready_timeout_s, source=source, extra_env=extra_env) as server:
        print(f"[{backend}] server {server.url} pid {server.process.pid} ready", flush=True)
        with FleetHealthClient(server.url, server.api_key, timeout=120.0) as client:
            # Warm-up: one stream through the whole path, so that memory figures exclude imports.
            warm_tail = f"BW-{run_id}"
            client.create_aircraft(warm_tail)
            client.create_actuator(warm_tail, "warm", channels=["current", "voltage"])
            t_s, channels = make_stream(args.batch_samples, seed=0, t0=1.7e9)
            ack = client.post_batch(warm_tail, "warm", "warm-0", channels, t_s=t_s, fmt="arrow")
            client.wait_applied(warm_tail, "warm", int(ack["seq"]), timeout_s=args.timeout_s)

            if args.idle_streams > 0:
                idle_tail = f"BI-{run_id}"
                client.create_aircraft(idle_tail)
                before, after, per_stream = bench_memory(
                    server,
                    idle_tail,
                    args.idle_streams,
                    args.idle_batch_samples,
                    args.concurrency,
                    args.timeout_s,
                )
                memory = {
                    "rss_before_bytes": before,
                    "rss_after_bytes": after,
                    "streams": args.idle_streams,
                    "bytes_per_stream": per_stream,
                }
                print(
                    f"[{backend}] memory: {before / 2**20:.1f} MiB -> {after / 2**20:.1f} MiB "
                    f"for {args.idle_streams} streams = {per_stream / 1024:.2f} KiB/stream",
                    flush=True,
                )

            if args.post1 > 0:
                tail = f"BP-{run_id}"
                client.create_aircraft(tail)
                pid = server.process.pid
                cpu0 = tree_cpu_s(pid)
                rate["post1_sequential"] = bench_post1_sequential(server, tail, args.post1, args.timeout_s)
                cpu1 = tree_cpu_s(pid)
                threads1 = metric_by_label(server, "fleethealth_thread_cpu_seconds_total", "thread")
                rate["post1_concurrent"] = bench_post1_concurrent(
                    server, tail, args.post1_clients, args.post1_per_client, args.load_processes, args.timeout_s
                )
                cpu2 = tree_cpu_s(pid)
                threads2 = metric_by_label(server, "fleethealth_thread_cpu_seconds_total", "thread")
                if threads2:  # the server's own split (trees without the metric print nothing)
                    n = rate["post1_concurrent"]["requests"]
                    split = sorted(((1e3 * (v - threads1.get(k, 0.0)) / n, k) for k, v in threads2.items()),
                                   reverse=True)
                    print(f"[{backend}] post1_concurrent, server CPU ms/request by thread: "
                          + ", ".join(f"{k} {ms:.3f}" for ms, k in split if ms >= 0.0005), flush=True)
                rate["plain_write"] = bench_plain_write(server, f"W{run_id}-", max(50, args.post1 // 4))
                cpu3 = tree_cpu_s(pid)
                rate["floor_concurrent"] = bench_floor(
                    server, args.post1_clients, args.post1_per_client, args.load_processes
                )
                cpu4 = tree_cpu_s(pid)
                # Server CPU per request, the apply of each sample included (sequential case:
                # measured until the last one is applied).
                for name, used in (("post1_sequential", cpu1 - cpu0), ("post1_concurrent", cpu2 - cpu1),
                                   ("plain_write", cpu3 - cpu2), ("floor_concurrent", cpu4 - cpu3)):
                    rate[name]["server_cpu_ms"] = 1e3 * used / rate[name]["requests"]
                rate["fdatasync"] = bench_fdatasync(workdir)
                print(f"[{backend}] fdatasync of 4 KiB: median {rate['fdatasync']['median_ms']:.2f} ms, "
                      f"p99 {rate['fdatasync']['p99_ms']:.2f} ms", flush=True)
                for name, fig in rate.items():
                    if name == "fdatasync":
                        continue
                    print(f"[{backend}] {name}: {fig['per_s']:,.0f} requests/s, median "
                          f"{fig['median_ms']:.2f} ms, p99 {fig['p99_ms']:.2f} ms, server CPU "
                          f"{fig['server_cpu_ms']:.2f} ms/request, client CPU {fig['client_cpu_ms']:.2f} ms/request"
                          + (f", {fig['resent']:.0f} resent" if fig.get("resent") else ""), flush=True)

            tail = f"BS-{run_id}"
            client.create_aircraft(tail)
            for fmt in args.formats if args.batches > 0 else ():
                cpu0 = tree_cpu_s(server.process.pid)
                row = bench_single(
                    client, backend, tail, fmt, args.batches, args.batch_samples, args.timeout_s
                )
                row.server_cpu_s = tree_cpu_s(server.process.pid) - cpu0
                rows.append(row)
                print(
                    f"[{backend}] {row.case} {fmt}: {row.samples_per_s:,.0f} samples/s, server CPU "
                    f"{row.server_cpu_us_per_sample:.2f} us/sample", flush=True
                )

        if args.streams > 0 and args.batches > 0:
            tail = f"BM-{run_id}"
            with FleetHealthClient(server.url, server.api_key) as client:
                client.create_aircraft(tail)
            for fmt in args.formats:
                row = bench_many(
                    server,
                    backend,
                    tail,
                    fmt,
                    args.streams,
                    args.batches_per_stream,
                    args.batch_samples,
                    args.concurrency,
                    args.timeout_s,
                )
                rows.append(row)
                print(
                    f"[{backend}] {row.case} {fmt}: {row.samples_per_s:,.0f} samples/s, server CPU "
                    f"{row.server_cpu_us_per_sample:.2f} us/sample", flush=True
                )
        recent = recent_batches(server)
        if recent:
            print(f"[{backend}] applies that found their batch decoded in memory: "
                  f"{recent.get('hit', 0):.0f} hits, {recent.get('miss', 0):.0f} decoded from the log "
                  f"({recent.get('not_held', 0):.0f} batches not held: the bound was reached)", flush=True)
        groups = metric_by_label(server, "fleethealth_apply_groups_total", "path")
        if groups:
            print(f"[{backend}] apply transactions: " + ", ".join(f"{v:.0f} {k}" for k, v in sorted(groups.items())),
                  flush=True)
    return {"rows": rows, "memory": memory, "rate": rate, "recent": recent}


def recent_batches(server: Server) -> dict[str, float]:
    """The server's ``fleethealth_recent_batches_total`` by outcome (empty when it has none)."""
    return metric_by_label(server, "fleethealth_recent_batches_total", "outcome")


def metric_by_label(server: Server, name: str, label: str) -> dict[str, float]:
    """A counter of the server's ``/metrics`` by one label (empty when it has none; a sample
    without labels, such as a histogram's ``_count``, under ``""``)."""
    import httpx

    text = httpx.get(server.url + "/metrics", headers={"Authorization": f"Bearer {server.api_key}"},
                     timeout=30.0).text
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line.startswith(name + "{"):
            value = line.split(f'{label}="', 1)[1].split('"', 1)[0]
            out[value] = float(line.rsplit(" ", 1)[1])
        elif line.startswith(name + " "):
            out[""] = float(line.rsplit(" ", 1)[1])
    return out


def print_table(results: dict[str, dict]) -> None:
    """Each figure per run label (``sqlite``, or ``sqlite base`` / ``sqlite new`` side by side)."""
    labels = list(results)
    print()
    print("Message rate (one sample per POST; a plain write = POST /v1/aircraft)")
    print(f"{'case':<44}" + "".join(f"{lab:>22}" for lab in labels) + f"{'goal':>22}")
    cases = [
        ("post1_sequential", "per_s", "1 client, sequential: requests/s", None),
        ("post1_sequential", "median_ms", "1 client, sequential: median ms", "<= 2 ms"),
        ("fdatasync", "median_ms", "fdatasync of 4 KiB (this disk): median ms", None),
        ("post1_sequential", "p99_ms", "1 client, sequential: p99 ms", None),
        ("post1_sequential", "server_cpu_ms", "1 client: server CPU ms/request", None),
        ("post1_concurrent", "per_s", "32 clients: requests/s", ">= 3,000/s"),
        ("post1_concurrent", "median_ms", "32 clients: median ms", None),
        ("post1_concurrent", "server_cpu_ms", "32 clients: server CPU ms/request", None),
        ("plain_write", "median_ms", "plain write, sequential: median ms", None),
        ("plain_write", "server_cpu_ms", "plain write: server CPU ms/request", None),
        ("post1_concurrent", "client_cpu_ms", "32 clients: client CPU ms/request", None),
        ("floor_concurrent", "per_s", "ceiling, GET /healthz, 32 clients: req/s", None),
        ("floor_concurrent", "server_cpu_ms", "GET /healthz: server CPU ms/request", None),
        ("floor_concurrent", "client_cpu_ms", "GET /healthz: client CPU ms/request", None),
    ]
    for key, field, text, goal in cases:
        vals = [results[lab].get("rate", {}).get(key, {}).get(field) for lab in labels]
        if all(v is None for v in vals):
            continue
        cells = "".join(f"{'-' if v is None else f'{v:,.2f}' if field.endswith('ms') else f'{v:,.0f}':>22}"
                        for v in vals)
        print(f"{text:<44}{cells}{goal or '-':>22}")
    print("The load client is bench/http_load.py (prebuilt HTTP/1.1 keep-alive requests); the ceiling is what "
          "the server answers for GET /healthz (no key, no database) with the same client; server CPU includes "
          "the apply of every sample (the POST cases wait until all are applied).")
    print()
    print("End-to-end ingest, samples/s: POST -> telemetry log -> FAKF applied -> results committed")
    keyed: dict[tuple[str, str], dict[str, Row]] = {}
    for lab, result in results.items():
        for row in result["rows"]:
            keyed.setdefault((row.case, row.fmt), {})[lab] = row
    print(f"{'case':<14}{'format':<8}" + "".join(f"{lab:>22}" for lab in labels) + f"{'goal':>14}")
    for (case, fmt), by_label in keyed.items():
        goal = GOALS_SAMPLES_S.get(fmt)
        cells = "".join(
            f"{by_label[lab].samples_per_s:>22,.0f}" if lab in by_label else f"{'-':>22}" for lab in labels
        )
        print(f"{case:<14}{fmt:<8}{cells}{(f'{goal:,}' if goal else '-'):>14}")
    print()
    print("Server CPU per sample, us (user + system of the server process during the case; the rate "
          "above is what the machine gave, this is what each sample cost)")
    print(f"{'case':<14}{'format':<8}" + "".join(f"{lab:>22}" for lab in labels))
    for (case, fmt), by_label in keyed.items():
        cells = "".join(
            f"{by_label[lab].server_cpu_us_per_sample:>22.3f}" if lab in by_label else f"{'-':>22}" for lab in labels
        )
        print(f"{case:<14}{fmt:<8}{cells}")
    print()
    for lab, result in results.items():
        memory = result["memory"]
        if memory:
            print(
                f"{lab}: server memory per registered stream (RSS delta / "
                f"{memory['streams']} streams): {memory['bytes_per_stream'] / 1024:.2f} KiB "
                f"(goal <= {GOAL_BYTES_PER_IDLE_STREAM / 1024:.0f} KiB per idle stream; one delta, "
                "first burst included: the slope over fleet sizes is bench/bench_stream_memory.py)"
            )
    print(f"For scale: NASA prog_server handles about {PROG_SERVER_SAMPLES_S} samples/s.")
    print(
        "Samples are time stamps carrying 2 channels. The client runs on the same 2 cores as the "
        "server; 'base' is the --baseline source tree, 'new' this checkout, both running at the same time."
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pg", default=None, help="also run against this PostgreSQL URL")
    parser.add_argument(
        "--baseline-pg", default=None,
        help="PostgreSQL URL of the --baseline run (default --pg); another database or schema "
             "(?options=-csearch_path%%3Dname) when the two trees' migrations differ",
    )
    parser.add_argument("--no-sqlite", action="store_true", help="skip the SQLite run")
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS))
    parser.add_argument("--batch-samples", type=int, default=10_000)
    parser.add_argument("--batches", type=int, default=30, help="batches in the 1-stream case")
    parser.add_argument("--streams", type=int, default=100)
    parser.add_argument("--batches-per-stream", type=int, default=2)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--idle-streams", type=int, default=1000)
    parser.add_argument("--idle-batch-samples", type=int, default=100)
    parser.add_argument("--timeout-s", type=float, default=600.0, help="limit for each wait")
    parser.add_argument("--ready-timeout-s", type=float, default=120.0)
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    parser.add_argument("--json-out", type=Path, default=None, help="also write figures here")
    parser.add_argument("--post1", type=int, default=1000, help="one-sample POSTs, sequential client")
    parser.add_argument("--post1-clients", type=int, default=32)
    parser.add_argument("--post1-per-client", type=int, default=100)
    parser.add_argument("--load-processes", type=int, default=2,
                        help="client processes of the concurrent message-rate cases (bench/http_load.py)")
    parser.add_argument(
        "--baseline", type=Path, default=None,
        help="also run the same cases against this source tree (e.g. git worktree add /tmp/base main), side by side",
    )
    parser.add_argument(
        "--apply-modes", action="store_true",
        help="SQLite twice, one after the other: the processor in a thread of serve "
             "(FLEETHEALTH_APPLY_PROCESS=off) and in its apply process (on, the default); this tree only",
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.batches, args.streams, args.batches_per_stream, args.idle_streams = 3, 10, 1, 50
        args.post1, args.post1_per_client = 200, 20

    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="fleethealth-bench-") as tmp:
        workdir = Path(tmp)
        runs: list[tuple[str, Path | None]] = [("", None)]
        if args.baseline is not None:
            runs = [(" base", args.baseline.resolve()), (" new", None)]

        def backend_runs(suffix: str, source: Path | None) -> None:
            if not args.no_sqlite:
                url = f"sqlite:///{workdir / f'bench{suffix.strip()}.db'}"
                if args.apply_modes and source is None:
                    for mode, label in (("off", "sqlite thread"), ("on", "sqlite apply-process")):
                        url = f"sqlite:///{workdir / f'bench{suffix.strip()}-{mode}.db'}"
                        results[f"{label}{suffix}"] = run_backend(
                            f"{label}{suffix}", url, workdir, args, source,
                            extra_env={"FLEETHEALTH_APPLY_PROCESS": mode})
                else:
                    results[f"sqlite{suffix}"] = run_backend(f"sqlite{suffix}", url, workdir, args, source)
            if args.pg:
                pg = args.baseline_pg if source is not None and args.baseline_pg else args.pg
                results[f"postgres{suffix}"] = run_backend(f"postgres{suffix}", pg, workdir, args, source)

        # Base and new at the same time, so that whatever else loads the machine weighs on both
        # alike (one after the other, a change of load would read as a change of speed).
        import threading

        threads = [threading.Thread(target=backend_runs, args=run) for run in runs]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        order = [f"{b}{suffix}" for b in ("sqlite", "sqlite thread", "sqlite apply-process", "postgres")
                 for suffix, _ in runs]
        results = {k: results[k] for k in order if k in results}
    print_table(results)
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            backend: {
                "rows": [asdict(row) | {"samples_per_s": row.samples_per_s,
                                         "server_cpu_us_per_sample": row.server_cpu_us_per_sample}
                         for row in r["rows"]],
                "memory": r["memory"],
                "rate": r.get("rate", {}),
                "recent": r.get("recent", {}),
            }
            for backend, r in results.items()
        }
        args.json_out.write_text(json.dumps(payload, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
