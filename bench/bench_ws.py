"""WebSocket streaming benchmark against a real ``fleethealth serve`` process on 127.0.0.1.

Measured, per frame size (samples per frame; two channels, ``current`` and ``voltage``, FAKF
attached):

* one connection: frames per second and samples per second from the first frame sent until the
  result of the last one is received (every frame logged durably, applied, result pushed back),
  with the library's :class:`~fleethealth_client.FrameStreamer`;
* many connections (``--streams``, and ``--many``, default 1,000; each to its own actuator, all
  at once): the same in aggregate. Every connection is open before the clock starts (the
  handshakes are not timed), and the clients are lean (frames encoded beforehand, the raw
  ``websockets`` protocol, at most ``--window`` frames awaiting results per connection,
  default 4) and spread over ``--client-procs`` processes, so that the server is what is
  measured: the client's CPU per frame is printed beside the server's;
* latency: from a frame sent to its result received, median and 99th percentile, for frames sent
  one at a time (nothing queued ahead of them), so it is the added latency of the path: parse,
  durable append (fsync), apply, commit, push.

Usage::

    .venv/bin/python bench/bench_ws.py            # SQLite in a temporary folder
    .venv/bin/python bench/bench_ws.py --quick
    git worktree add /tmp/base main && .venv/bin/python bench/bench_ws.py --baseline /tmp/base

With ``--baseline`` both servers run at once (and each side's clients in their own processes),
so that they share whatever else loads the machine alike. Figures are printed; nothing is
asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import orjson

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_ingest import make_stream, running_server, tree_cpu_s  # noqa: E402
from fleethealth_client import FleetHealthClient, FrameStreamer, encode_frame, frames_of  # noqa: E402
from fleethealth_client.paths import actuator_path, ws_url  # noqa: E402

FAKF = {"fakf": {"identification_samples": 1000, "health_window_samples": 1000}}
Frames = list[tuple[Any, dict[str, Any]]]


def _setup(url: str, key: str, tail: str, n: int) -> None:
    with FleetHealthClient(url, key) as client:
        client.create_aircraft(tail)
        for k in range(n):
            client.create_actuator(tail, f"a{k:04d}", estimators=FAKF)


# ----------------------------------------------------------------------------- one connection
async def _stream(url: str, key: str, tail: str, act: str, frames: Frames) -> None:
    async with FrameStreamer(url, key, tail, act, binary=True) as fs:
        for t, chans in frames:
            await fs.send(chans, t_s=t)
        await fs.drain(600)
        assert len(fs.stats.results) == len(frames), "results missing"


def one_connection(url: str, key: str, tail: str, frames: Frames) -> float:
    t0 = time.perf_counter()
    asyncio.run(_stream(url, key, tail, "a0000", frames))
    return time.perf_counter() - t0


def latency(url: str, key: str, tail: str, frames: Frames) -> np.ndarray:
    async def run() -> list[float]:
        out = []
        async with FrameStreamer(url, key, tail, "a0000", binary=True) as fs:
            for t, chans in frames:
                n = len(fs.stats.results)
                t0 = time.perf_counter()
                await fs.send(chans, t_s=t)
                await fs.drain(60)
                assert len(fs.stats.results) == n + 1
                out.append(time.perf_counter() - t0)
        return out

    return np.asarray(asyncio.run(run()))


# ----------------------------------------------------------------------------- many connections
async def _lean_streams(url: str, key: str, tail: str, acts: list[str], frames: list[bytes], window: int,
                        pipe: Connection) -> tuple[float, float, float]:
    """Open every connection, tell the parent, wait for its go; then stream ``frames`` into
    each, at most ``window`` (and the server's ``max_inflight``) awaiting their results: a
    thousand connections with 16 frames each in flight would fill the server's process-wide
    read-ahead (8,192 frames; it stops reading, and a connection not read misses its keepalive
    pongs), with 4 they stay below half of it (no ``slow_down``). Returns (start, end, client
    CPU s)."""
    from websockets.asyncio.client import connect

    headers = {"Authorization": f"Bearer {key}"}
    conns = []
    # One after the other (a thousand handshakes at once only time out); no keepalive pings of
    # the client's (the server's own keep the connections checked).
    for act in acts:
        ws = await connect(ws_url(url, f"{actuator_path(tail, act)}/stream"), additional_headers=headers,
                           max_size=None, open_timeout=120, ping_interval=None)
        ready = orjson.loads(await ws.recv())
        assert ready["type"] == "ready", ready
        conns.append((ws, min(window, int(ready["max_inflight"]))))
    pipe.send("open")
    pipe.recv()  # go

    async def one(ws: Any, window: int) -> None:
        results = 0
        sent = 0
        while results < len(frames):
            while sent < len(frames) and sent - results < window:
                await ws.send(frames[sent])
                sent += 1
            msg = orjson.loads(await asyncio.wait_for(ws.recv(), 600))
            if msg["type"] == "result":
                results += 1
            elif msg["type"] == "error":
                raise RuntimeError(msg)
        await ws.close()

    cpu0 = time.process_time()
    start = time.time()
    await asyncio.gather(*(one(ws, w) for ws, w in conns))
    return start, time.time(), time.process_time() - cpu0


def _client_proc(url: str, key: str, tail: str, acts: list[str], frames: list[bytes], window: int,
                 pipe: Connection) -> None:
    try:
        pipe.send(asyncio.run(_lean_streams(url, key, tail, acts, frames, window, pipe)))
    except BaseException as exc:
        pipe.send(exc)
        raise


def many_connections(url: str, key: str, tail: str, n_streams: int, frames: Frames,
                     n_procs: int, window: int, server_pid: int,
                     at_go: Callable[[], None] | None = None) -> tuple[float, float, float]:
    """Wall seconds of the sending phase (first frame sent to last result received, over every
    client process), client and server CPU seconds of that phase (not of the handshakes).
    ``at_go``: called once every connection is open, just before the sending phase."""
    encoded = [encode_frame(i + 1, chans, t_s=t, binary=True) for i, (t, chans) in enumerate(frames)]
    assert all(isinstance(f, bytes) for f in encoded)
    acts = [f"a{k:04d}" for k in range(n_streams)]
    ctx = mp.get_context("spawn")
    procs = []
    for p in range(n_procs):
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_client_proc, args=(url, key, tail, acts[p::n_procs], encoded, window, child))
        proc.start()
        procs.append((proc, parent))
    for _, pipe in procs:
        got = pipe.recv()
        if isinstance(got, BaseException):
            raise got
    if at_go is not None:
        at_go()
    cpu0 = tree_cpu_s(server_pid)
    for _, pipe in procs:
        pipe.send("go")
    outs = [pipe.recv() for _, pipe in procs]
    server_cpu = tree_cpu_s(server_pid) - cpu0
    for proc, _ in procs:
        proc.join(60)
    for out in outs:
        if isinstance(out, BaseException):
            raise out
    return max(o[1] for o in outs) - min(o[0] for o in outs), sum(o[2] for o in outs), server_cpu


# ----------------------------------------------------------------------------- the cases
def run_all(args: argparse.Namespace, source: Path | None, env: dict[str, str] | None = None,
            label: str | None = None) -> dict[str, float]:
    """Every case against one server (this checkout, or the ``source`` tree; ``env`` added to
    its environment)."""
    n_frames = 100 if args.quick else 400
    label = label or ("base" if source else "new")
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        url_db = f"sqlite:///{Path(tmp) / 'ws.db'}"
        with running_server(url_db, Path(tmp), args.ready_timeout_s, source=source, extra_env=env) as server:
            url, key, pid = server.url, server.api_key, server.process.pid
            cases = [(10, 1), (10, args.streams), (10, args.many), (1000, 1)]
            for size, n_streams in cases:
                tail = f"T{size}x{n_streams}"
                _setup(url, key, tail, n_streams)
                t, chans = make_stream(size * n_frames, seed=size, t0=0.0)
                frames = frames_of(t, chans, size)
                if n_streams == 1:
                    cpu0 = tree_cpu_s(pid)
                    dt, client_cpu = one_connection(url, key, tail, frames), float("nan")
                    server_cpu = tree_cpu_s(pid) - cpu0
                else:
                    frames = frames[: args.frames_per_stream]
                    dt, client_cpu, server_cpu = many_connections(
                        url, key, tail, n_streams, frames, args.client_procs, args.window, pid
                    )
                nf = n_streams * len(frames)
                case = f"{size}x{n_streams}"
                out[f"{case} frames/s"] = nf / dt
                out[f"{case} server CPU ms/frame"] = 1e3 * server_cpu / nf
                if n_streams > 1:
                    out[f"{case} client CPU ms/frame"] = 1e3 * client_cpu / nf
                print(f"  [{label}] {size}-sample frames, {n_streams} connections: {nf / dt:,.0f} frames/s",
                      flush=True)
            tail = "L10"
            _setup(url, key, tail, 1)
            t, chans = make_stream(10 * 200, seed=7, t0=0.0)
            lat = latency(url, key, tail, frames_of(t, chans, 10)[:200])[20:]  # after warm-up
            out["10-sample frame to result: median ms"] = float(np.median(lat) * 1e3)
            out["10-sample frame to result: p99 ms"] = float(np.percentile(lat, 99) * 1e3)
    return out


def latency_rounds(args: argparse.Namespace) -> int:
    """Frame to result median at light load (one connection, one frame at a time), each tree's
    server alone, alternating; three streams per server."""
    trees: list[tuple[str, Path | None]] = [("new", None)]
    if args.baseline is not None:
        trees.insert(0, ("base", args.baseline.resolve()))
    medians: dict[str, list[float]] = {label: [] for label, _ in trees}
    for _ in range(args.latency_rounds):
        for label, source in trees:
            with tempfile.TemporaryDirectory(prefix="fleethealth-ws-lat-") as tmp, running_server(
                f"sqlite:///{Path(tmp) / 'lat.db'}", Path(tmp), args.ready_timeout_s, source=source
            ) as server:
                for k in range(3):
                    tail = f"L{k}"
                    _setup(server.url, server.api_key, tail, 1)
                    t, ch = make_stream(10 * 120, seed=7, t0=0.0)
                    lat = latency(server.url, server.api_key, tail, frames_of(t, ch, 10)[:120])[20:]
                    medians[label].append(float(np.median(lat) * 1e3))
    print("10-sample frame to result, median ms per stream (one server at a time, in turn)")
    for label, values in medians.items():
        print(f"  {label:<5} " + " ".join(f"{v:6.2f}" for v in values)
              + f"   median of medians {float(np.median(values)):.2f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--streams", type=int, default=200, help="connections of the many-connection case")
    ap.add_argument("--many", type=int, default=1000, help="connections of the largest case")
    ap.add_argument("--frames-per-stream", type=int, default=20)
    ap.add_argument("--client-procs", type=int, default=2, help="client processes of the many-connection cases")
    ap.add_argument("--window", type=int, default=4,
                    help="frames awaiting results per connection in the many-connection cases")
    ap.add_argument("--ready-timeout-s", type=float, default=600.0)
    ap.add_argument(
        "--baseline", type=Path, default=None,
        help="also run against this source tree (e.g. git worktree add /tmp/base main), side by side",
    )
    ap.add_argument("--latency-rounds", type=int, default=0,
                    help="only the light-load latency, one server at a time, base and new in turn "
                         "for this many rounds (side by side, both servers at once, each one's "
                         "latency depends on what the other is doing at that moment)")
    ap.add_argument("--apply-modes", action="store_true",
                    help="this tree twice, one after the other: the processor in a thread of serve "
                         "(FLEETHEALTH_APPLY_PROCESS=off) and in its apply process (on, the default)")
    args = ap.parse_args(argv)
    if args.latency_rounds:
        return latency_rounds(args)
    runs: dict[str, dict[str, float]] = {}
    if args.apply_modes:
        # One after the other: each mode's server has the machine to itself.
        for mode, label in (("off", "thread"), ("on", "apply-process")):
            runs[label] = run_all(args, None, {"FLEETHEALTH_APPLY_PROCESS": mode}, label)
    elif args.baseline is None:
        runs["new"] = run_all(args, None)
    else:
        # Both at once, so that they share whatever else loads the machine alike (run one after
        # the other, a change of load between the runs shows as a change of speed).
        def one(label: str, source: Path | None) -> None:
            try:
                runs[label] = run_all(args, source)
            except BaseException as exc:  # a thread drops SystemExit silently: say what failed
                print(f"  [{label}] failed: {exc!r}", flush=True)
                raise

        threads = [threading.Thread(target=one, args=("base", args.baseline.resolve())),
                   threading.Thread(target=one, args=("new", None))]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        if set(runs) != {"base", "new"}:
            return 1
        runs = {"base": runs["base"], "new": runs["new"]}
    print("\nWebSocket streaming, SQLite, FAKF attached, Arrow frames (frame -> logged -> applied -> result)")
    labels = list(runs)
    print(f"{'case':<44}" + "".join(f"{lab:>14}" for lab in labels))
    for case in runs[labels[-1]]:
        print(f"{case:<44}" + "".join(f"{runs[lab].get(case, float('nan')):>14,.2f}" for lab in labels))
    print("Goals: >= 10,000 frames/s of 10-sample frames over 1,000 connections; frame to result "
          "median <= 5 ms at light load. Server CPU = user + system seconds of the server process; "
          "client CPU = the client processes' (both sides' clients are this checkout's).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
