"""The ``fleethealth`` command."""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.config import Settings

DEMO_OPERATOR = "demo"


def _settings() -> Settings:
    from app.config import Settings

    return Settings()


def cmd_migrate(args: argparse.Namespace) -> int:
    from app.migrate import upgrade

    s = _settings()
    upgrade(s.database_url)
    print(f"database at head: {s.database_url}")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from app.main import create_app
    from app.migrate import upgrade

    s = _settings()
    host = args.host or s.host
    port = args.port or s.port
    if not args.no_migrate:
        upgrade(s.database_url)
    url = f"http://{host}:{port}"
    stop = threading.Event()
    if args.demo:
        from app.auth.service import SCOPES, create_key, ensure_key
        from app.db import Database

        db = Database(s.database_url)
        with db.write() as session:
            if s.bootstrap_admin_key:
                key = s.bootstrap_admin_key
                ensure_key(session, s.bootstrap_operator, key, list(SCOPES), name="bootstrap")
            else:
                _, key = create_key(session, DEMO_OPERATOR, list(SCOPES), name="demo")
        db.dispose()
        print(f"\n  fleethealth demo: {url}\n  API docs:        {url}/docs\n  demo API key:    {key}\n"
              f"  try: curl -H 'Authorization: Bearer {key}' {url}/v1/fleet/health\n", flush=True)
        threading.Thread(target=_demo_feeder, args=(url, key, stop), daemon=True).start()
    else:
        print(f"fleethealth serving on {url} (API docs at {url}/docs)", flush=True)
    config = uvicorn.Config(
        create_app(s),
        host=host,
        port=port,
        log_level=args.log_level,
        ws_max_size=s.ws_max_frame_bytes,
        ws_ping_interval=s.ws_ping_interval_s,
        ws_ping_timeout=s.ws_ping_timeout_s,
        timeout_graceful_shutdown=math.ceil(s.shutdown_timeout_s),
    )
    try:
        uvicorn.Server(config).run(sockets=[_listen(host, port, s.socket_send_buffer_bytes)])
    finally:
        stop.set()
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    """Apply pending batches in this process, next to any number of API and worker processes
    sharing one PostgreSQL (docs/scaling.md)."""
    import signal

    from app.db import Database
    from app.main import warm_kernels
    from app.processing import wakeups
    from app.processing.processor import Processor

    s = _settings()
    db = Database(s.database_url)
    if db.is_sqlite:
        db.dispose()
        print("fleethealth worker needs PostgreSQL (FLEETHEALTH_DATABASE_URL); with SQLite the "
              "processor runs inside `fleethealth serve`", file=sys.stderr)
        return 2
    if s.warm_kernels:
        warm_kernels()
    chans = wakeups.channels(db)
    processor = Processor(db, s.model_copy(update={"processor_enabled": True}),
                          applied_channel=chans.applied, origin=wakeups.ORIGIN)
    listener = wakeups.Listener(s.database_url, chans, on_logged=processor.notify_many,
                                on_resync=processor.recover)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    listener.start()
    listener.listening.wait(30)
    processor.start()
    print(f"fleethealth worker {wakeups.ORIGIN} applying streams of {db.engine.url.render_as_string()}",
          flush=True)
    try:
        while not stop.wait(1.0):
            if not processor.running:
                print("the processor thread stopped", file=sys.stderr)
                return 1
    finally:
        listener.stop()
        processor.stop(timeout=s.shutdown_timeout_s)
        db.dispose()
    return 0


def _listen(host: str, port: int, send_buffer_bytes: int | None) -> socket.socket:
    """The listening socket. Accepted connections inherit its send buffer size, so a cap here
    bounds the kernel memory a slow reader can hold (and disables send-buffer autotuning)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer_bytes is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
    sock.bind((host, port))
    sock.set_inheritable(True)
    return sock


def _demo_feeder(url: str, key: str, stop: threading.Event) -> None:
    try:
        from fleethealth_tools.simulate import run_simulation

        # Waits for /readyz itself. Every second aircraft's flight controls get surface faults;
        # the taxi drives wear out at different rates.
        run_simulation(url, key, stop_event=stop, flight_controls=True, friction_drives=True)
    except Exception as exc:  # the demo feeder must never take the server down
        print(f"demo simulator stopped: {exc}", file=sys.stderr)


def cmd_keys(args: argparse.Namespace) -> int:
    from app.auth.service import create_key, list_keys, parse_scopes, revoke_key
    from app.db import Database

    db = Database(_settings().database_url)
    try:
        if args.keys_cmd == "create":
            with db.write() as s:
                row, plaintext = create_key(s, args.operator, parse_scopes(args.scopes), name=args.name)
                print(plaintext)
                print(f"created key {row.id} ({row.prefix}...) for operator {args.operator!r} "
                      f"with scopes {row.scopes}", file=sys.stderr)
        elif args.keys_cmd == "list":
            with db.read() as s:
                for key, op in list_keys(s):
                    state = "revoked" if key.revoked_at else "active"
                    print(f"{key.id}\t{op}\t{key.prefix}...\t{key.scopes}\t{state}\t{key.name}")
        elif args.keys_cmd == "revoke":
            with db.write() as s:
                if not revoke_key(s, args.id):
                    print(f"no key {args.id}", file=sys.stderr)
                    return 1
                print(f"revoked key {args.id}")
    finally:
        db.dispose()
    return 0


def cmd_streams(args: argparse.Namespace) -> int:
    from app.db import Database
    from app.processing.service import failed_streams, reset_failed

    db = Database(_settings().database_url)
    try:
        if args.streams_cmd == "failed":
            with db.read() as s:
                for operator, tail, actuator_id, reason in failed_streams(s):
                    print(f"{operator}\t{tail}\t{actuator_id}\t{reason}")
        elif args.streams_cmd == "reset":
            with db.write() as s:
                if not reset_failed(s, args.operator, args.tail, args.actuator_id):
                    print(f"{args.tail}/{args.actuator_id} is not marked failed", file=sys.stderr)
                    return 1
            print(f"reset {args.tail}/{args.actuator_id}; the processor applies it again")
    finally:
        db.dispose()
    return 0


def openapi_document() -> dict[str, Any]:
    from app.config import Settings
    from app.main import create_app

    return create_app(Settings(database_url="sqlite://")).openapi()


def cmd_export_openapi(args: argparse.Namespace) -> int:
    text = json.dumps(openapi_document(), indent=2, sort_keys=True) + "\n"
    if args.output == "-":
        sys.stdout.write(text)
    else:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(text)
        print(f"wrote {args.output}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fleethealth", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    sp = sub.add_parser("serve", help="apply migrations and serve the API")
    sp.add_argument("--host", default=None, help="default: FLEETHEALTH_HOST or 127.0.0.1")
    sp.add_argument("--port", type=int, default=None, help="default: FLEETHEALTH_PORT or 8000")
    sp.add_argument("--demo", action="store_true", help="also feed a simulated demo fleet")
    sp.add_argument("--no-migrate", action="store_true", help="do not apply migrations first")
    sp.add_argument("--log-level", default="info")
    sp.set_defaults(func=cmd_serve)

    sp = sub.add_parser("worker", help="apply pending batches (PostgreSQL; any number of workers)")
    sp.set_defaults(func=cmd_worker)

    sp = sub.add_parser("migrate", help="apply database migrations up to head")
    sp.set_defaults(func=cmd_migrate)

    sp = sub.add_parser("keys", help="manage API keys")
    ks = sp.add_subparsers(dest="keys_cmd", required=True)
    kc = ks.add_parser("create", help="create a key and print it (once)")
    kc.add_argument("--operator", required=True)
    kc.add_argument("--scopes", default="ingest,read", help="comma-separated: ingest,read,admin")
    kc.add_argument("--name", default="")
    ks.add_parser("list", help="list keys (never the keys themselves)")
    kr = ks.add_parser("revoke", help="revoke a key by id")
    kr.add_argument("id", type=int)
    sp.set_defaults(func=cmd_keys)

    sp = sub.add_parser("streams", help="streams marked failed (no longer applied)")
    ss = sp.add_subparsers(dest="streams_cmd", required=True)
    ss.add_parser("failed", help="list failed streams with the reason")
    sr = ss.add_parser("reset", help="clear a stream's failed mark so it is applied again")
    sr.add_argument("--operator", required=True)
    sr.add_argument("tail")
    sr.add_argument("actuator_id")
    sp.set_defaults(func=cmd_streams)

    sp = sub.add_parser("export-openapi", help="write the OpenAPI document")
    sp.add_argument("--output", "-o", default="openapi/openapi.json", help="file, or - for stdout")
    sp.set_defaults(func=cmd_export_openapi)

    from fleethealth_tools.commands import add_subcommands

    add_subcommands(sub)  # simulate, replay
    return p


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
