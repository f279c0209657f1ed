"""WebSocket streaming benchmark against a real ``fleethealth serve`` process on 127.0.0.1.

Measured, per frame size (samples per frame; two channels, ``current`` and ``voltage``, FAKF
attached):

* one connection: frames per second and samples per second from the first frame sent until the
  result of the last one is received (every frame logged durably, applied, result pushed back);
* many connections (``--streams``, each to its own actuator, all at once): the same in aggregate;
* latency: from a frame sent to its result received, median and 99th percentile, for frames sent
  one at a time (nothing queued ahead of them), so it is the added latency of the path: parse,
  durable append (fsync), apply, commit, push.

Usage::

    .venv/bin/python bench/bench_ws.py            # SQLite in a temporary folder
    .venv/bin/python bench/bench_ws.py --quick
    git worktree add /tmp/base main && .venv/bin/python bench/bench_ws.py --baseline /tmp/base

Figures are printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_ingest import make_stream, running_server, tree_cpu_s  # noqa: E402
from fleethealth_client import FleetHealthClient, FrameStreamer, frames_of  # noqa: E402

FAKF = {"fakf": {"identification_samples": 1000, "health_window_samples": 1000}}


def _setup(url: str, key: str, tail: str, n: int) -> None:
    with FleetHealthClient(url, key) as client:
        client.create_aircraft(tail)
        for k in range(n):
            client.create_actuator(tail, f"a{k:03d}", estimators=FAKF)


async def _stream(url: str, key: str, tail: str, act: str, frames: list, binary: bool) -> None:  # type: ignore[type-arg]
    async with FrameStreamer(url, key, tail, act, binary=binary) as fs:
        for t, chans in frames:
            await fs.send(chans, t_s=t)
        await fs.drain(600)
        assert len(fs.stats.results) == len(frames), "results missing"


def throughput(url: str, key: str, tail: str, n_streams: int, frames: list, binary: bool) -> float:  # type: ignore[type-arg]
    async def run() -> None:
        await asyncio.gather(*(_stream(url, key, tail, f"a{k:03d}", frames, binary) for k in range(n_streams)))

    t0 = time.perf_counter()
    asyncio.run(run())
    return time.perf_counter() - t0


def latency(url: str, key: str, tail: str, frames: list) -> np.ndarray:  # type: ignore[type-arg]
    async def run() -> list[float]:
        out = []
        async with FrameStreamer(url, key, tail, "a000", binary=True) as fs:
            for t, chans in frames:
                n = len(fs.stats.results)
                t0 = time.perf_counter()
                await fs.send(chans, t_s=t)
                await fs.drain(60)
                assert len(fs.stats.results) == n + 1
                out.append(time.perf_counter() - t0)
        return out

    return np.asarray(asyncio.run(run()))


def run_all(args: argparse.Namespace, source: Path | None) -> dict[str, float]:
    """Every case against one server (this checkout, or the ``source`` tree)."""
    n_frames = 100 if args.quick else 400
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        url_db = f"sqlite:///{Path(tmp) / 'ws.db'}"
        with running_server(url_db, Path(tmp), args.ready_timeout_s, source=source) as server:
            url, key, pid = server.url, server.api_key, server.process.pid
            for size in (10, 1000):
                for n_streams in (1, args.streams):
                    if size == 1000 and n_streams > 1:
                        continue
                    tail = f"T{size}x{n_streams}"
                    _setup(url, key, tail, n_streams)
                    t, chans = make_stream(size * n_frames, seed=size, t0=0.0)
                    frames = frames_of(t, chans, size)
                    if n_streams > 1:
                        frames = frames[: args.frames_per_stream]
                    cpu0 = tree_cpu_s(pid)
                    dt = throughput(url, key, tail, n_streams, frames, binary=True)
                    nf = n_streams * len(frames)
                    out[f"{size}x{n_streams} frames/s"] = nf / dt
                    out[f"{size}x{n_streams} server CPU ms/frame"] = 1e3 * (tree_cpu_s(pid) - cpu0) / nf
                    print(f"  [{'base' if source else 'new'}] {size}-sample frames, {n_streams} connections: "
                          f"{nf / dt:,.0f} frames/s", flush=True)
            tail = "L10"
            _setup(url, key, tail, 1)
            t, chans = make_stream(10 * 200, seed=7, t0=0.0)
            lat = latency(url, key, tail, frames_of(t, chans, 10)[:200])[20:]  # after warm-up
            out["10-sample frame to result: median ms"] = float(np.median(lat) * 1e3)
            out["10-sample frame to result: p99 ms"] = float(np.percentile(lat, 99) * 1e3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--streams", type=int, default=200, help="connections of the many-connection case")
    ap.add_argument("--frames-per-stream", type=int, default=20)
    ap.add_argument("--ready-timeout-s", type=float, default=600.0)
    ap.add_argument(
        "--baseline", type=Path, default=None,
        help="also run against this source tree (e.g. git worktree add /tmp/base main), side by side",
    )
    args = ap.parse_args(argv)
    runs: dict[str, dict[str, float]] = {}
    if args.baseline is None:
        runs["new"] = run_all(args, None)
    else:
        # Both at once, so that they share whatever else loads the machine alike (run one after
        # the other, a change of load between the runs shows as a change of speed).
        import threading

        def one(label: str, source: Path | None) -> None:
            runs[label] = run_all(args, source)

        threads = [threading.Thread(target=one, args=("base", args.baseline.resolve())),
                   threading.Thread(target=one, args=("new", None))]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        runs = {"base": runs["base"], "new": runs["new"]}
    print("\nWebSocket streaming, SQLite, FAKF attached, Arrow frames (frame -> logged -> applied -> result)")
    labels = list(runs)
    print(f"{'case':<44}" + "".join(f"{lab:>14}" for lab in labels))
    for case in runs["new"]:
        print(f"{case:<44}" + "".join(f"{runs[lab].get(case, float('nan')):>14,.2f}" for lab in labels))
    print("Goals: >= 10,000 frames/s of 10-sample frames over 1,000 connections; frame to result "
          "median <= 5 ms at light load. Server CPU = user + system seconds of the server process.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
