"""Overload soak of the WebSocket ingest against a real ``fleethealth serve`` on 127.0.0.1.

1. Calibrate: every stream sends as fast as the server lets it (the client paces itself by the
   server's ``slow_down`` / ``resume``); the sustainable rate is the results delivered per second.
2. Load: every stream offers frames on a fixed schedule at ``--factor`` (default 2) times its
   share of that rate for ``--duration`` seconds; nothing is skipped when the server throttles,
   the frames are sent late. Then every stream drains (all results back).
3. Idle: the server is left alone for ``--idle`` seconds.

Printed: the server's resident memory and the frames queued in it (``fleethealth_ws_queued_frames``)
every second through the three phases; frames offered, sent, logged and their results; reconnects
(connections beyond the first per stream: the dropped connections), slow_down / resume notices,
seconds spent throttled, and how long after the load ended the last result arrived.

Usage::

    .venv/bin/python bench/soak/ws_overload.py                       # 100 streams, SQLite
    .venv/bin/python bench/soak/ws_overload.py --streams 20 --duration 10 --idle 5   # quick

Figures are printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

from bench_ingest import make_stream, running_server  # noqa: E402
from fleethealth_client import FleetHealthClient, FrameStreamer  # noqa: E402

FAKF = {"fakf": {"identification_samples": 1000, "health_window_samples": 1000}}
TAIL = "SOAK"


@dataclass
class StreamOutcome:
    sent: int = 0
    results: int = 0
    connects: int = 0
    slow_downs: int = 0
    resumes: int = 0
    throttled_s: float = 0.0
    last_result_at: float = 0.0
    error: str | None = None


@dataclass
class Sampler:
    """Server RSS and queued frames, once a second, from another thread."""

    pid: int
    url: str
    key: str
    phase: str = "start"
    rows: list[tuple[float, str, float, float]] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def queued(self) -> float:
        try:
            text = httpx.get(f"{self.url}/metrics", headers={"Authorization": f"Bearer {self.key}"},
                             timeout=5).text
        except httpx.HTTPError:
            return float("nan")
        for line in text.splitlines():
            if line.startswith("fleethealth_ws_queued_frames "):
                return float(line.split()[1])
        return 0.0

    def run(self) -> None:
        t0 = time.monotonic()
        while not self.stop.is_set():
            self.rows.append((time.monotonic() - t0, self.phase, self.rss_mb(), self.queued()))
            self.stop.wait(1.0)


def _frames(k: int, n_frames: int, samples: int, t0: float) -> list[tuple[Any, dict[str, Any]]]:
    t, ch = make_stream(n_frames * samples, seed=k, t0=t0)
    return [(t[i : i + samples], {c: v[i : i + samples] for c, v in ch.items()})
            for i in range(0, n_frames * samples, samples)]


async def _one(url: str, key: str, act: str, frames: list[Any], rate_hz: float | None,
               out: StreamOutcome, binary: bool) -> None:
    loop = asyncio.get_running_loop()
    try:
        async with FrameStreamer(url, key, TAIL, act, binary=binary) as fs:
            start = loop.time()
            for i, (t, ch) in enumerate(frames):
                if rate_hz is not None:  # the offered schedule; late frames are sent late
                    await asyncio.sleep(max(0.0, start + i / rate_hz - loop.time()))
                await fs.send(ch, t_s=t)
                out.sent += 1
            await fs.drain(900)
            out.last_result_at = time.monotonic()
            out.results += len(fs.stats.results)
            out.connects += fs.stats.connects
            out.slow_downs += fs.stats.slow_downs
            # (getattr: the same script measures clients from before throttling existed)
            out.resumes += getattr(fs.stats, "resumes", 0)
            out.throttled_s += getattr(fs.stats, "throttled_s", 0.0)
    except Exception as exc:  # reported, never hidden
        out.error = f"{type(exc).__name__}: {exc}"


def _phase(url: str, key: str, n_streams: int, frames: list[list[Any]], rate_hz: float | None,
           binary: bool) -> tuple[list[StreamOutcome], float]:
    outs = [StreamOutcome() for _ in range(n_streams)]

    async def run() -> None:
        await asyncio.gather(*(_one(url, key, f"s{k:03d}", frames[k], rate_hz, outs[k], binary)
                               for k in range(n_streams)))

    t0 = time.monotonic()
    asyncio.run(run())
    return outs, time.monotonic() - t0


def _summary(name: str, outs: list[StreamOutcome], elapsed_s: float, load_end: float | None) -> None:
    sent = sum(o.sent for o in outs)
    results = sum(o.results for o in outs)
    reconnects = sum(max(0, o.connects - 1) for o in outs)
    errors = [o.error for o in outs if o.error]
    print(f"{name}: {len(outs)} streams, {sent} frames sent, {results} results "
          f"({results / elapsed_s:.1f}/s over {elapsed_s:.1f} s), reconnects {reconnects}, "
          f"slow_down {sum(o.slow_downs for o in outs)}, resume {sum(o.resumes for o in outs)}, "
          f"throttled {sum(o.throttled_s for o in outs):.0f} stream-s, errors {len(errors)}")
    if load_end is not None:
        last = max(o.last_result_at for o in outs)
        print(f"  last result {last - load_end:.1f} s after the load ended")
    for e in errors[:5]:
        print(f"  error: {e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, default=100)
    ap.add_argument("--samples", type=int, default=100, help="samples per frame")
    ap.add_argument("--calibrate-frames", type=int, default=20, help="frames per stream to calibrate")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of load")
    ap.add_argument("--factor", type=float, default=2.0, help="offered / sustainable rate")
    ap.add_argument("--idle", type=float, default=20.0, help="seconds idle after the load")
    ap.add_argument("--binary", action="store_true", help="Arrow frames instead of JSON")
    ap.add_argument("--database-url", default=None, help="default: SQLite in a temporary folder")
    ap.add_argument("--ready-timeout", type=float, default=300.0)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="fh-soak-") as tmp:
        workdir = Path(tmp)
        url_db = args.database_url or f"sqlite:///{workdir / 'soak.db'}"
        os.environ.setdefault("FLEETHEALTH_WS_PING_INTERVAL_S", "5")  # keepalive checked often
        os.environ.setdefault("FLEETHEALTH_WS_PING_TIMEOUT_S", "10")
        with running_server(url_db, workdir, args.ready_timeout) as server:
            with FleetHealthClient(server.url, server.api_key) as c:
                c.create_aircraft(TAIL)
                for k in range(args.streams):
                    c.create_actuator(TAIL, f"s{k:03d}", estimators=FAKF)
            sampler = Sampler(server.process.pid, server.url, server.api_key)
            threading.Thread(target=sampler.run, daemon=True).start()
            print(f"server {server.url}, database {url_db.split('?')[0]}, pid {server.process.pid}")

            sampler.phase = "calibrate"
            cal = [_frames(k, args.calibrate_frames, args.samples, 0.0) for k in range(args.streams)]
            outs, elapsed = _phase(server.url, server.api_key, args.streams, cal, None, args.binary)
            _summary("calibration (as fast as allowed)", outs, elapsed, None)
            sustainable = sum(o.results for o in outs) / elapsed
            per_stream = args.factor * sustainable / args.streams
            n_frames = max(1, int(per_stream * args.duration))
            print(f"sustainable {sustainable:.1f} frames/s ({sustainable * args.samples:.0f} samples/s); "
                  f"offering {args.factor:g}x: {per_stream:.2f} frames/s per stream, {n_frames} frames each")

            sampler.phase = "load"
            t_start = args.calibrate_frames * args.samples / 1000.0 + 1.0
            load = [_frames(k, n_frames, args.samples, t_start) for k in range(args.streams)]
            load_end = time.monotonic() + n_frames / per_stream
            outs, elapsed = _phase(server.url, server.api_key, args.streams, load, per_stream, args.binary)
            _summary(f"load ({args.factor:g}x sustainable, then drain)", outs, elapsed, load_end)
            expected = args.streams * n_frames
            print(f"  results {sum(o.results for o in outs)} of {expected} frames; "
                  f"dropped connections {sum(max(0, o.connects - 1) for o in outs)}")

            sampler.phase = "idle"
            time.sleep(args.idle)
            sampler.stop.set()
            time.sleep(1.1)

    print("\n  t_s  phase       rss_MB  queued_frames")
    for t, phase, rss, queued in sampler.rows:
        print(f"{t:5.0f}  {phase:10s} {rss:7.1f}  {queued:6.0f}")
    by_phase: dict[str, list[float]] = {}
    for _, phase, rss, _ in sampler.rows:
        by_phase.setdefault(phase, []).append(rss)
    print("peak RSS by phase: " + ", ".join(f"{p} {max(v):.0f} MB" for p, v in by_phase.items()))
    if "idle" in by_phase:
        print(f"RSS at the end of idle: {by_phase['idle'][-1]:.0f} MB")


if __name__ == "__main__":
    main()
