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

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.applied_s if self.applied_s > 0 else float("nan")


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


@contextmanager
def running_server(database_url: str, workdir: Path, ready_timeout_s: float) -> Iterator[Server]:
    """Migrate the database, start ``fleethealth serve`` and stop it (and only it) at the end."""
    api_key = secrets.token_urlsafe(24)
    env = dict(os.environ)
    env.update(
        {
            "FLEETHEALTH_DATABASE_URL": database_url,
            "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": api_key,
        }
    )
    exe = fleethealth_exe()
    migrate = subprocess.run(
        [exe, "migrate"], env=env, cwd=workdir, capture_output=True, text=True, timeout=300
    )
    if migrate.returncode != 0:
        raise SystemExit(f"fleethealth migrate failed:\n{migrate.stdout}\n{migrate.stderr}")
    port = free_port()
    log_path = workdir / f"server-{port}.log"
    log_file = open(log_path, "wb")  # noqa: SIM115 - closed in finally
    process = subprocess.Popen(
        [exe, "serve", "--host", "127.0.0.1", "--port", str(port)],
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


def tree_rss_bytes(pid: int) -> int:
    """Resident memory of a process and its descendants, from /proc."""
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
    total, stack = 0, [pid]
    while stack:
        current = stack.pop()
        with contextlib.suppress(OSError):  # the process ended meanwhile
            for line in Path(f"/proc/{current}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        stack.extend(children.get(current, []))
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
) -> tuple[float, float]:
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
            await asyncio.sleep(0.02)
        return ack_s, time.perf_counter() - start


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
    ack_s, applied_s = asyncio.run(
        _bench_many_async(
            server, tail, fmt, streams, n_batches, batch_samples, concurrency, timeout_s
        )
    )
    samples = streams * n_batches * batch_samples
    return Row(backend, f"{streams} streams", fmt, streams, samples, ack_s, applied_s)


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


def run_backend(backend: str, database_url: str, workdir: Path, args: argparse.Namespace) -> dict:
    rows: list[Row] = []
    memory: dict[str, float] = {}
    run_id = secrets.token_hex(3).upper()
    with running_server(database_url, workdir, args.ready_timeout_s) as server:
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

            tail = f"BS-{run_id}"
            client.create_aircraft(tail)
            for fmt in args.formats:
                row = bench_single(
                    client, backend, tail, fmt, args.batches, args.batch_samples, args.timeout_s
                )
                rows.append(row)
                print(
                    f"[{backend}] {row.case} {fmt}: {row.samples_per_s:,.0f} samples/s", flush=True
                )

        if args.streams > 0:
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
                    f"[{backend}] {row.case} {fmt}: {row.samples_per_s:,.0f} samples/s", flush=True
                )
    return {"rows": rows, "memory": memory}


def print_table(results: dict[str, dict]) -> None:
    print()
    print("End-to-end ingest: POST -> telemetry log -> FAKF applied -> results committed")
    print(
        f"{'backend':<8} {'case':<12} {'format':<6} {'samples':>10} {'ack s':>8} "
        f"{'applied s':>10} {'samples/s':>12} {'goal':>11} {'client encode/s':>16}"
    )
    for result in results.values():
        for row in result["rows"]:
            goal = GOALS_SAMPLES_S.get(row.fmt)
            goal_text = f"{goal:,}" if goal else "-"
            encode_rate = row.samples / row.encode_s if row.encode_s > 0 else float("nan")
            encode_text = "-" if encode_rate != encode_rate else f"{encode_rate:,.0f}"
            print(
                f"{row.backend:<8} {row.case:<12} {row.fmt:<6} {row.samples:>10,} "
                f"{row.ack_s:>8.2f} {row.applied_s:>10.2f} {row.samples_per_s:>12,.0f} "
                f"{goal_text:>11} {encode_text:>16}"
            )
    print()
    for backend, result in results.items():
        memory = result["memory"]
        if memory:
            print(
                f"{backend}: server memory per registered stream (RSS delta / "
                f"{memory['streams']} streams): {memory['bytes_per_stream'] / 1024:.2f} KiB "
                f"(goal < {GOAL_BYTES_PER_IDLE_STREAM / 1024:.0f} KiB per idle stream)"
            )
    print(f"For scale: NASA prog_server handles about {PROG_SERVER_SAMPLES_S} samples/s.")
    print(
        "Samples are time stamps carrying 2 channels; 'ack s' = all batches acknowledged "
        "(durable in the log), 'applied s' = FAKF applied and committed; 'client encode/s' = "
        "the client's encoding alone (excluded from the timings)."
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pg", default=None, help="also run against this PostgreSQL URL")
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
    args = parser.parse_args(argv)
    if args.quick:
        args.batches, args.streams, args.batches_per_stream, args.idle_streams = 3, 10, 1, 50

    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="fleethealth-bench-") as tmp:
        workdir = Path(tmp)
        if not args.no_sqlite:
            url = f"sqlite:///{workdir / 'bench.db'}"
            results["sqlite"] = run_backend("sqlite", url, workdir, args)
        if args.pg:
            results["postgres"] = run_backend("postgres", args.pg, workdir, args)
    print_table(results)
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            backend: {
                "rows": [asdict(row) | {"samples_per_s": row.samples_per_s} for row in r["rows"]],
                "memory": r["memory"],
            }
            for backend, r in results.items()
        }
        args.json_out.write_text(json.dumps(payload, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
