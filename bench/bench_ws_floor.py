"""The floor of the WebSocket stack on this machine: frames per second with no application work.

The 10,000 frames/s goal (10-sample frames over 1,000 connections, two cores, the load clients
on the same cores) is measured by :mod:`bench_ws`. This bench asks what the same clients reach
against a server that does nothing with a frame: a bare ASGI application under the same uvicorn
(uvloop, the ``websockets`` protocol, the settings ``fleethealth serve`` uses) that answers each
binary frame with the protocol's two small JSON messages (``logged`` and ``result``; with
``--one-reply`` only ``result``), without reading it, logging it or applying it. What it reaches
bounds what any server built on this stack can reach here, whatever its application does.

Per run, one server at a time, in turn (``--runs`` rounds): the floor server, then
``fleethealth serve`` (SQLite in a temporary folder, FAKF attached), each against the lean
clients of :mod:`bench_ws` (``--client-procs`` processes, ``--window`` frames awaiting their
results per connection). Printed: frames/s, server and client CPU per frame (``/proc``), and the
ratio of the floor to the service.

Usage::

    .venv/bin/python bench/bench_ws_floor.py --runs 2

Figures are printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_ws  # noqa: E402
from bench_ingest import _stop, free_port, make_stream, running_server  # noqa: E402
from fleethealth_client import frames_of  # noqa: E402

from app.config import Settings  # noqa: E402

#: The floor server: a bare ASGI application, run by uvicorn with ``fleethealth serve``'s
#: WebSocket settings (passed as arguments). It reads no frame: a ``ready`` message on connect,
#: then per received message the replies, of the sizes the service sends.
FLOOR_APP = r"""
import sys
import orjson
import uvicorn

READY = orjson.dumps({"type": "ready", "max_inflight": 16, "max_frame_bytes": 16777216})
ONE_REPLY = sys.argv[2] == "1"


async def app(scope, receive, send):
    if scope["type"] == "lifespan":
        while True:
            msg = await receive()
            if msg["type"] == "lifespan.startup":
                await send({"type": "lifespan.startup.complete"})
            elif msg["type"] == "lifespan.shutdown":
                await send({"type": "lifespan.shutdown.complete"})
                return
    if scope["type"] != "websocket":
        await send({"type": "http.response.start", "status": 404, "headers": []})
        await send({"type": "http.response.body", "body": b""})
        return
    await receive()  # websocket.connect
    await send({"type": "websocket.accept"})
    await send({"type": "websocket.send", "text": READY.decode()})
    seq = 0
    while True:
        msg = await receive()
        if msg["type"] != "websocket.receive":
            return
        seq += 1
        if not ONE_REPLY:
            await send({"type": "websocket.send", "text": orjson.dumps({
                "type": "logged", "client_seq": seq, "seq": seq, "n_samples": 10,
                "t_first_s": 0.0, "t_last_s": 0.09}).decode()})
        await send({"type": "websocket.send", "text": orjson.dumps({
            "type": "result", "client_seq": seq, "seq": seq, "t_last_s": 0.09,
            "samples": {"voltage_estimate": [0.0] * 10}, "health": [], "events": []}).decode()})


s = sys.argv[3:]
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning",
            ws_max_size=int(s[0]), ws_ping_interval=float(s[1]), ws_ping_timeout=float(s[2]),
            ws_per_message_deflate=s[3] == "1")
"""


@contextmanager
def floor_server(one_reply: bool, ready_timeout_s: float) -> Iterator[tuple[str, int]]:
    """Start the floor server; yield its URL and pid; stop it."""
    st = Settings()
    port = free_port()
    args = [
        str(st.ws_max_frame_bytes),
        str(st.ws_ping_interval_s),
        str(st.ws_ping_timeout_s),
        "1" if st.ws_per_message_deflate else "0",
    ]
    proc = subprocess.Popen(
        [sys.executable, "-c", FLOOR_APP, str(port), "1" if one_reply else "0", *args],
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + ready_timeout_s
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1.0):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("the floor server did not start") from None
                time.sleep(0.05)
        yield f"http://127.0.0.1:{port}", proc.pid
    finally:
        _stop(proc)


def measure(
    url: str, key: str, tail: str, pid: int, args: argparse.Namespace, frames: bench_ws.Frames
) -> tuple[float, float, float]:
    """frames/s, server CPU ms per frame, client CPU ms per frame."""
    dt, client_cpu, server_cpu = bench_ws.many_connections(
        url, key, tail, args.connections, frames, args.client_procs, args.window, pid
    )
    nf = args.connections * len(frames)
    return nf / dt, 1e3 * server_cpu / nf, 1e3 * client_cpu / nf


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1, help="rounds of floor then service, in turn")
    ap.add_argument("--connections", type=int, default=1000)
    ap.add_argument("--frames-per-stream", type=int, default=20)
    ap.add_argument("--client-procs", type=int, default=2)
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument(
        "--one-reply",
        action="store_true",
        help="the floor server sends only the result message per frame",
    )
    ap.add_argument("--no-service", action="store_true", help="measure the floor server only")
    ap.add_argument("--ready-timeout-s", type=float, default=600.0)
    args = ap.parse_args(argv)
    t, chans = make_stream(10 * args.frames_per_stream, seed=10, t0=0.0)
    frames = frames_of(t, chans, 10)[: args.frames_per_stream]
    rows: dict[str, list[tuple[float, float, float]]] = {"floor": [], "service": []}
    print(
        f"{args.connections} connections x {len(frames)} 10-sample frames, {os.cpu_count()} cores",
        flush=True,
    )
    for r in range(args.runs):
        with floor_server(args.one_reply, args.ready_timeout_s) as (url, pid):
            rows["floor"].append(measure(url, "unused", "F", pid, args, frames))
        print(f"  run {r + 1} floor:   {rows['floor'][-1][0]:8,.0f} frames/s", flush=True)
        if args.no_service:
            continue
        with (
            tempfile.TemporaryDirectory(prefix="fleethealth-ws-floor-") as tmp,
            running_server(
                f"sqlite:///{Path(tmp) / 'ws.db'}", Path(tmp), args.ready_timeout_s
            ) as server,
        ):
            bench_ws._setup(server.url, server.api_key, "S", args.connections)
            rows["service"].append(
                measure(server.url, server.api_key, "S", server.process.pid, args, frames)
            )
        print(f"  run {r + 1} service: {rows['service'][-1][0]:8,.0f} frames/s", flush=True)
    print("\n| | frames/s | server CPU ms/frame | client CPU ms/frame |")
    print("| --- | --- | --- | --- |")
    label = "floor (one reply)" if args.one_reply else "floor (two replies)"
    for name, vals in rows.items():
        for i, (fps, scpu, ccpu) in enumerate(vals):
            shown = label if name == "floor" else "fleethealth serve"
            print(f"| {shown}, run {i + 1} | {fps:,.0f} | {scpu:.3f} | {ccpu:.3f} |")
    if rows["service"]:
        ratios = [f[0] / s[0] for f, s in zip(rows["floor"], rows["service"], strict=True)]
        print("\nfloor / service, frames/s: " + ", ".join(f"{x:.2f}" for x in ratios))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
