"""The ``fleethealth`` command."""

from __future__ import annotations

import argparse
import errno
import getpass
import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.config import Settings

DEMO_OPERATOR = "demo"
#: Settings of ``serve --demo`` unless given by their FLEETHEALTH_* variable: applied batches'
#: raw payloads are dropped after ten minutes and per-sample outputs keep the last 15 minutes of
#: each stream, so that the demo's database stays small (docs/operations.md, "The demo").
DEMO_DEFAULTS: dict[str, object] = {"log_retention_s": 600.0, "sample_output_retention_s": 900.0}


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
    s = _settings()
    host = args.host or s.host
    port = args.port or s.port
    # Bind first: a busy port is one clear line before anything else happens.
    try:
        sock = _listen(host, port, s.socket_send_buffer_bytes)
    except OSError as exc:
        print(f"fleethealth: cannot listen on {host}:{port}: {exc.strerror or exc}"
              + (" (is another fleethealth running? pick another port with --port or FLEETHEALTH_PORT)"
                 if exc.errno == errno.EADDRINUSE else ""), file=sys.stderr)
        return 1
    import uvicorn

    from app.main import create_app
    from app.migrate import upgrade

    _log_to_stderr(args.log_level)
    if args.demo:
        s = _demo_settings(s)
    if not args.no_migrate:
        upgrade(s.database_url)
    url = f"http://{host}:{port}"
    feeder: subprocess.Popen[bytes] | None = None
    if args.demo:
        from app.auth.service import SCOPES, create_key, ensure_key
        from app.db import Database

        db = Database(s.database_url)
        with db.write() as session:
            if s.bootstrap_admin_key:
                key, operator = s.bootstrap_admin_key, s.bootstrap_operator
                ensure_key(session, operator, key, list(SCOPES), name="bootstrap")
            else:
                operator = DEMO_OPERATOR
                _, key = create_key(session, operator, list(SCOPES), name="demo")
        db.dispose()
        print(f"\n  fleethealth demo: {url}\n  API docs:        {url}/docs\n  demo API key:    {key}\n"
              f"  the demo fleet belongs to operator {operator!r}: keys of other operators do not see it;\n"
              f"  more keys for it: fleethealth keys create --operator {operator} --scopes read\n"
              f"  try: curl -H 'Authorization: Bearer {key}' {url}/v1/fleet/health\n", flush=True)
        feeder = _start_demo_feeder(url, key)
    else:
        print(f"fleethealth serving on {url} (API docs at {url}/docs)", flush=True)
    access_log = args.access_log if args.access_log is not None else not args.demo
    config = uvicorn.Config(
        create_app(s),
        host=host,
        port=port,
        log_level=args.log_level,
        access_log=access_log,
        ws_max_size=s.ws_max_frame_bytes,
        ws_ping_interval=s.ws_ping_interval_s,
        ws_ping_timeout=s.ws_ping_timeout_s,
        ws_per_message_deflate=s.ws_per_message_deflate,
        timeout_graceful_shutdown=math.ceil(s.shutdown_timeout_s),
    )
    server = uvicorn.Server(config) if feeder is None else _demo_server(config, feeder)
    try:
        server.run(sockets=[sock])
    finally:
        if feeder is not None:
            _stop_demo_feeder(feeder)
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    """Apply pending batches in this process, next to any number of API and worker processes
    sharing one PostgreSQL (docs/scaling.md)."""
    import signal
    import threading

    from app.db import Database
    from app.kernels import KernelWarmup
    from app.processing import wakeups
    from app.processing.processor import Processor
    from estimators.registry import ESTIMATORS

    s = _settings()
    db = Database(s.database_url)
    if db.is_sqlite:
        db.dispose()
        print("fleethealth worker needs PostgreSQL (FLEETHEALTH_DATABASE_URL); with SQLite the "
              "processor runs in `fleethealth serve`'s apply process (FLEETHEALTH_APPLY_PROCESS)",
              file=sys.stderr)
        return 2
    chans = wakeups.channels(db)
    # Streams are applied as soon as their kinds' kernels are ready (app/kernels.py).
    kernels = KernelWarmup(list(ESTIMATORS), processes=s.warm_kernels_processes, enabled=s.warm_kernels)
    processor = Processor(db, s.model_copy(update={"processor_enabled": True}),
                          applied_channel=chans.applied, origin=wakeups.ORIGIN,
                          ready_kinds=kernels.applicable_kinds)

    def _kind_ready(_kind: str) -> None:
        processor.recover()  # wake the streams that waited for this kind

    kernels.on_ready = _kind_ready
    listener = wakeups.Listener(s.database_url, chans, on_logged=processor.notify_many,
                                on_resync=processor.recover)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    listener.start()
    listener.listening.wait(30)
    processor.start()
    kernels.start()
    print(f"fleethealth worker {wakeups.ORIGIN} applying streams of {db.engine.url.render_as_string()}",
          flush=True)
    try:
        while not stop.wait(1.0):
            if not processor.running:
                print("the processor thread stopped", file=sys.stderr)
                return 1
    finally:
        kernels.stop()
        listener.stop()
        processor.stop(timeout=s.shutdown_timeout_s)
        db.dispose()
    return 0


def _demo_settings(s: Settings) -> Settings:
    """The demo's settings: those given, with retention defaults that keep its database small."""
    demo = {name: value for name, value in DEMO_DEFAULTS.items() if f"FLEETHEALTH_{name}".upper() not in os.environ}
    return s.model_copy(update=demo)


def _log_to_stderr(level: str) -> None:
    """The service's own messages (kernels ready, streams failed, the demo) on stderr."""
    import logging

    logger = logging.getLogger("fleethealth")
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(levelname)s:     %(name)s: %(message)s"))
        logger.addHandler(handler)
    logger.setLevel(level.upper() if level.upper() in logging.getLevelNamesMapping() else logging.INFO)


def _listen(host: str, port: int, send_buffer_bytes: int | None) -> socket.socket:
    """The listening socket. Accepted connections inherit its send buffer size, so a cap here
    bounds the kernel memory a slow reader can hold (and disables send-buffer autotuning)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer_bytes is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
    sock.bind((host, port))
    # Listen at once: with SO_REUSEADDR a second process could still bind a port that is bound
    # but not listening yet.
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def _start_demo_feeder(url: str, key: str) -> subprocess.Popen[bytes]:
    """``fleethealth simulate`` in a child process: its plant simulations (and their first
    numba compile) run beside the server rather than in its interpreter. It waits for the
    server itself; every second aircraft's flight controls get surface faults and the taxi
    drives wear out at different rates. Its stdout is the terminal's; it stops when the server
    stops, or when its stdin closes (the server died)."""
    return subprocess.Popen(
        [sys.executable, "-m", "app.cli", "simulate", "--url", url, "--flight-controls",
         "--friction-drives", "--stop-on-stdin-eof"],
        stdin=subprocess.PIPE,
        env={**os.environ, "FLEETHEALTH_API_KEY": key},  # not on the command line (ps shows it)
    )


def _demo_server(config: Any, feeder: subprocess.Popen[bytes]) -> Any:
    """uvicorn's server, stopping the demo feeder first when it shuts down (uvicorn ends the
    process by re-raising SIGTERM once shut down, so a ``finally`` after ``run`` may not run)."""
    import uvicorn

    class DemoServer(uvicorn.Server):
        async def shutdown(self, sockets: Any = None) -> None:
            _stop_demo_feeder(feeder)
            await super().shutdown(sockets)

    return DemoServer(config)


def _stop_demo_feeder(feeder: subprocess.Popen[bytes]) -> None:
    if feeder.poll() is None:
        feeder.terminate()
        try:
            feeder.wait(5)
        except subprocess.TimeoutExpired:
            feeder.kill()
            feeder.wait()


def cmd_keys(args: argparse.Namespace) -> int:
    from app.auth.service import create_key, list_keys, parse_scopes, revoke_key, set_scopes
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
        elif args.keys_cmd == "scopes":
            with db.write() as s:
                if not set_scopes(s, args.id, parse_scopes(args.scopes)):
                    print(f"no key {args.id}", file=sys.stderr)
                    return 1
                print(f"key {args.id} now has scopes {','.join(parse_scopes(args.scopes))}")
    finally:
        db.dispose()
    return 0


def cmd_streams(args: argparse.Namespace) -> int:
    from app.db import Database
    from app.errors import DomainError
    from app.processing.service import failed_streams, reset_failed

    db = Database(_settings().database_url)
    try:
        return _streams(args, db, failed_streams, reset_failed)
    except DomainError as exc:
        print(f"{exc.name}: {exc.detail}", file=sys.stderr)
        return 1
    finally:
        db.dispose()


def _streams(args: argparse.Namespace, db: Any, failed_streams: Any, reset_failed: Any) -> int:
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
    elif args.streams_cmd == "rewind":
        from app.streams.service import actuator_by_name, rewind

        actor = f"cli {getpass.getuser()}@{socket.gethostname()}"
        with db.write() as s:
            act = actuator_by_name(s, args.operator, args.tail, args.actuator_id, lock=True)
            row = rewind(s, act, args.to_seq, args.reason, actor=actor, key_id=None)
            print(_rewind_text(row))
        print("running servers re-read the stream's applied mark from the database; a "
              "`?wait=` in flight there may end early", file=sys.stderr)
    elif args.streams_cmd == "rewinds":
        from app.streams.service import actuator_by_name, rewinds

        with db.read() as s:
            for row in rewinds(s, actuator_by_name(s, args.operator, args.tail, args.actuator_id)):
                print(_rewind_text(row))
    return 0


def cmd_webhooks(args: argparse.Namespace) -> int:
    from app.db import Database
    from app.errors import DomainError
    from app.webhooks.service import allow_target, disallow_target, targets_by_name

    db = Database(_settings().database_url)
    try:
        if args.webhooks_cmd == "allow":
            with db.write() as s:
                print(f"allowed {allow_target(s, args.operator, args.prefix)} for {args.operator!r}")
        elif args.webhooks_cmd == "disallow":
            with db.write() as s:
                if not disallow_target(s, args.operator, args.prefix):
                    print(f"{args.prefix} was not allowed for {args.operator!r}", file=sys.stderr)
                    return 1
            print(f"disallowed {args.prefix}; deliveries to URLs under it now fail")
        elif args.webhooks_cmd == "targets":
            with db.read() as s:
                for prefix in targets_by_name(s, args.operator):
                    print(prefix)
    except DomainError as exc:
        print(exc.detail, file=sys.stderr)
        return 1
    finally:
        db.dispose()
    return 0


def _rewind_text(row: Any) -> str:
    seqs = [d["seq"] for d in row.discarded]
    ids = ", ".join(d["batch_id"] for d in row.discarded[:10]) + (" ..." if len(seqs) > 10 else "")
    return (f"rewind {row.id} at {row.at.isoformat()} by {row.actor}: kept 1..{row.to_seq}, discarded "
            f"{len(seqs)} batches (seq {seqs[0] if seqs else '-'}..{seqs[-1] if seqs else '-'}: {ids}); "
            f"estimators {'restarted' if row.estimators_reset else 'kept'}; reason: {row.reason}")


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
    sp.add_argument("--access-log", action=argparse.BooleanOptionalAction, default=None,
                    help="one line per request (default: on, off with --demo)")
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
    kq = ks.add_parser("scopes", help="replace a key's scopes (open connections that lose theirs close)")
    kq.add_argument("id", type=int)
    kq.add_argument("scopes", help="comma-separated: ingest,read,admin")
    sp.set_defaults(func=cmd_keys)

    sp = sub.add_parser("streams", help="streams marked failed (no longer applied), rewinds")
    ss = sp.add_subparsers(dest="streams_cmd", required=True)
    ss.add_parser("failed", help="list failed streams with the reason")
    sr = ss.add_parser("reset", help="clear a stream's failed mark so it is applied again")
    sr.add_argument("--operator", required=True)
    sr.add_argument("tail")
    sr.add_argument("actuator_id")
    sw = ss.add_parser("rewind", help="discard a stream's batches after --to-seq (recorded; the "
                       "estimators restart when they had applied one)")
    sw.add_argument("--operator", required=True)
    sw.add_argument("--to-seq", type=int, required=True, help="keep batches 1..TO_SEQ")
    sw.add_argument("--reason", required=True, help="why (kept in the record)")
    sw.add_argument("tail")
    sw.add_argument("actuator_id")
    sl = ss.add_parser("rewinds", help="list a stream's rewinds")
    sl.add_argument("--operator", required=True)
    sl.add_argument("tail")
    sl.add_argument("actuator_id")
    sp.set_defaults(func=cmd_streams)

    sp = sub.add_parser("webhooks", help="URL prefixes an operator's webhooks may deliver to")
    ws = sp.add_subparsers(dest="webhooks_cmd", required=True)
    for name, text in (("allow", "allow a URL prefix"), ("disallow", "remove an allowed prefix")):
        wa = ws.add_parser(name, help=text)
        wa.add_argument("--operator", required=True)
        wa.add_argument("prefix", help="e.g. https://hooks.example.com/fleethealth")
    wt = ws.add_parser("targets", help="list the allowed prefixes")
    wt.add_argument("--operator", required=True)
    sp.set_defaults(func=cmd_webhooks)

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
