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

from bench_ingest import make_stream, running_server  # noqa: E402
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--streams", type=int, default=50)
    args = ap.parse_args(argv)
    n_frames = 100 if args.quick else 400
    sizes = (10, 100, 1000)
    with tempfile.TemporaryDirectory() as tmp:
        url_db = f"sqlite:///{Path(tmp) / 'ws.db'}"
        with running_server(url_db, Path(tmp), 180.0) as server:
            url, key = server.url, server.api_key
            print(f"WebSocket streaming, SQLite, FAKF attached; {n_frames} frames per connection\n")
            print(f"{'frame':>6} {'format':>6} {'conns':>5} {'frames/s':>10} {'samples/s':>11}")
            for size in sizes:
                for binary in (False, True):
                    fmt = "arrow" if binary else "json"
                    for n_streams in (1, args.streams):
                        tail = f"T{size}{fmt}{n_streams}"
                        _setup(url, key, tail, n_streams)
                        t, chans = make_stream(size * n_frames, seed=size, t0=0.0)
                        frames = frames_of(t, chans, size)
                        if n_streams > 1:
                            frames = frames[: max(10, n_frames // 10)]
                        dt = throughput(url, key, tail, n_streams, frames, binary)
                        nf = n_streams * len(frames)
                        print(f"{size:>6} {fmt:>6} {n_streams:>5} {nf / dt:>10.0f} {nf * size / dt:>11.0f}")
            print("\nLatency, frame sent -> result received, one frame at a time (Arrow frames):")
            for size in sizes:
                tail = f"L{size}"
                _setup(url, key, tail, 1)
                t, chans = make_stream(size * 200, seed=7, t0=0.0)
                lat = latency(url, key, tail, frames_of(t, chans, size)[:200])[20:]  # after warm-up
                print(
                    f"  {size:>5} samples/frame: median {np.median(lat) * 1e3:.2f} ms, "
                    f"p99 {np.percentile(lat, 99) * 1e3:.2f} ms (n={lat.size})"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
