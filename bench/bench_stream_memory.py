"""Server memory per idle registered stream: the slope over several fleet sizes, with a breakdown.

A real ``fleethealth serve`` on 127.0.0.1 (SQLite in a temporary folder, and PostgreSQL with
``--pg``) is warmed by one stream, then streams are registered in steps (default 1,000, 5,000,
10,000 and 20,000 in all); each new stream gets one small Arrow batch, posted with ``?wait=`` so
that it is applied before the step ends. After each step the server is left alone for
``--settle-s`` seconds (default 35, past the actuator look-up cache's 30 s TTL), one batch is
posted to the warm stream (the idle streams sit beside a live one), and the server is asked,
through a probe loaded in front of ``app.cli`` (``SIGUSR1``, nothing of it in the service), for
a snapshot of its memory:

* RSS and ``/proc/self/smaps`` split into the brk heap, anonymous mappings (thread arenas,
  pymalloc arenas, large blocks) and file mappings;
* glibc ``mallinfo2`` (bytes in use, bytes free but kept in the arenas) and the arena count
  (``malloc_info``);
* Python: allocated blocks, gc-tracked objects, the most numerous types, optionally the top
  tracemalloc lines (``--tracemalloc``: slower, and its own bookkeeping inflates RSS);
* SQLite's own allocator (``sqlite3_memory_used``, page cache) when the backend is SQLite;
* the entries of the service's in-process per-stream structures (the look-up caches, the
  processor's marks, the hub), found by type.

The slope of each figure against the number of streams (least squares over the steps) is what
stays resident per idle stream; the first step's delta over the warmed server also contains
what any first burst grows once. ``--baseline DIR`` runs the same against another source tree,
at the same time, side by side.

Usage::

    .venv/bin/python bench/bench_stream_memory.py                      # SQLite
    .venv/bin/python bench/bench_stream_memory.py --pg postgresql://postgres@127.0.0.1:5432/test \\
        --baseline /tmp/base
    .venv/bin/python bench/bench_stream_memory.py --steps 500 1000 --quick-settle

Figures are printed (and written as JSON with ``--json-out``); nothing is asserted.
"""

from __future__ import annotations

import os
import signal
import sys

PROBE_FLAG = "--probe-serve"
PROBE_OUT_ENV = "FLEETHEALTH_MEMPROBE_OUT"
PROBE_TRACE_ENV = "FLEETHEALTH_MEMPROBE_TRACEMALLOC"
# In-process structures whose per-stream entries are reported (type name -> attributes).
PROBED_TYPES = {
    "TtlCache": ("_entries",),
    "Processor": ("_applied", "_meta", "_attempts", "_retry_at", "_recheck_at"),
    "Hub": ("_streams", "_waiters", "_fleet"),
    "RecentBatches": ("_items",),
}


# ------------------------------------------------------------------------------------------------
# The probe: runs inside the server process (``bench_stream_memory.py --probe-serve serve ...``)
# ------------------------------------------------------------------------------------------------


def _smaps() -> dict[str, int]:
    """Resident and anonymous bytes per kind of mapping, from /proc/self/smaps."""
    out = {"heap_rss": 0, "anon_rss": 0, "file_rss": 0, "stack_rss": 0, "anonymous": 0}
    kind = "file_rss"
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split(None, 1)[0]
            if "-" in head and not head.endswith(":"):  # a mapping's first line
                parts = line.split()
                name = parts[5] if len(parts) > 5 else ""
                kind = ("heap_rss" if name == "[heap]" else "stack_rss" if name.startswith("[stack")
                        else "anon_rss" if name == "" or name.startswith("[anon") else "file_rss")
            elif head == "Rss:":
                out[kind] += int(line.split()[1]) * 1024
            elif head == "Anonymous:":
                out["anonymous"] += int(line.split()[1]) * 1024
    return out


def _glibc() -> dict[str, int]:
    import ctypes
    import ctypes.util
    import re
    import tempfile

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    out: dict[str, int] = {}

    class Mallinfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
            "fordblks", "keepcost")]

    try:
        libc.mallinfo2.restype = Mallinfo2
        mi = libc.mallinfo2()
    except AttributeError:  # glibc < 2.33
        return out
    out |= {"malloc_arena_bytes": mi.arena, "malloc_mmap_bytes": mi.hblkhd,
            "malloc_in_use_bytes": mi.uordblks, "malloc_free_bytes": mi.fordblks,
            "malloc_free_chunks": mi.ordblks}
    libc.fopen.restype = ctypes.c_void_p
    libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
    libc.fclose.argtypes = [ctypes.c_void_p]
    libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
    with tempfile.NamedTemporaryFile(suffix=".xml") as tmp:
        fp = libc.fopen(tmp.name.encode(), b"w")
        if fp:
            libc.malloc_info(0, fp)
            libc.fclose(fp)
            xml = open(tmp.name).read()  # noqa: SIM115 - read at once
            out["malloc_arenas"] = len(re.findall(r"<heap nr=", xml))
    return out


def _sqlite() -> dict[str, int]:
    import ctypes
    import ctypes.util

    try:
        lib = ctypes.CDLL("libsqlite3.so.0")  # the library _sqlite3 links (same process state)
    except OSError:
        return {}
    lib.sqlite3_memory_used.restype = ctypes.c_int64
    cur, hi = ctypes.c_int64(), ctypes.c_int64()
    lib.sqlite3_status64.argtypes = [ctypes.c_int, ctypes.POINTER(ctypes.c_int64),
                                     ctypes.POINTER(ctypes.c_int64), ctypes.c_int]
    lib.sqlite3_status64(2, ctypes.byref(cur), ctypes.byref(hi), 0)  # SQLITE_STATUS_PAGECACHE_OVERFLOW
    return {"sqlite_memory_used": int(lib.sqlite3_memory_used()), "sqlite_pagecache_bytes": cur.value}


def _python(top_types: int = 12) -> tuple[dict[str, int], dict[str, int], dict[str, dict[str, int]]]:
    import collections
    import gc

    objects = gc.get_objects()
    counts = collections.Counter(type(o).__name__ for o in objects)
    structures: dict[str, dict[str, int]] = {}
    for o in objects:
        attrs = PROBED_TYPES.get(type(o).__name__)
        if attrs is None:
            continue
        name = type(o).__name__
        if name == "TtlCache":
            name = f"TtlCache#{sum(1 for k in structures if k.startswith('TtlCache'))}"
        structures[name] = {a: len(getattr(o, a)) for a in attrs if hasattr(o, a)}
    figures = {"py_allocated_blocks": sys.getallocatedblocks(), "gc_objects": len(objects)}
    return figures, dict(counts.most_common(top_types)), structures


def _snapshot() -> dict[str, object]:
    import threading
    import tracemalloc

    rss = 0
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024
    figures: dict[str, int] = {"rss_self": rss, "threads": threading.active_count()}
    figures |= _smaps()
    figures |= _glibc()
    figures |= _sqlite()
    py, types, structures = _python()
    figures |= py
    out: dict[str, object] = {"figures": figures, "types": types, "structures": structures}
    if tracemalloc.is_tracing():
        snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
        figures["tracemalloc_bytes"] = tracemalloc.get_traced_memory()[0]
        out["tracemalloc_top"] = {str(s.traceback[0]): s.size for s in snap.statistics("lineno")[:15]}
    return out


def probe_serve(argv: list[str]) -> int:
    import json

    out_path = os.environ[PROBE_OUT_ENV]
    if os.environ.get(PROBE_TRACE_ENV) == "1":
        import tracemalloc

        tracemalloc.start(1)
    count = [0]

    def on_signal(_signum: int, _frame: object) -> None:
        count[0] += 1
        snap = _snapshot() | {"n": count[0]}
        with open(out_path + ".tmp", "w") as f:
            json.dump(snap, f)
        os.replace(out_path + ".tmp", out_path)

    signal.signal(signal.SIGUSR1, on_signal)
    from app.cli import main

    return main(argv)


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == PROBE_FLAG:
    raise SystemExit(probe_serve(sys.argv[2:]))


# ------------------------------------------------------------------------------------------------
# The driver
# ------------------------------------------------------------------------------------------------

import argparse  # noqa: E402
import asyncio  # noqa: E402
import json  # noqa: E402
import secrets  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ingest import (  # noqa: E402
    GOAL_BYTES_PER_IDLE_STREAM,
    ROOT,
    Server,
    _stop,
    _wait_ready,
    free_port,
    make_stream,
    tree_rss_bytes,
)
from fleethealth_client import AsyncFleetHealthClient, FleetHealthClient  # noqa: E402

# Figures whose slope is printed, in this order (bytes per stream).
SLOPE_ROWS = [
    ("rss", "RSS (server process tree)"),
    ("rss_self", "RSS (server process alone)"),
    ("anonymous", "  anonymous memory (smaps)"),
    ("heap_rss", "  brk heap resident"),
    ("anon_rss", "  anonymous mappings resident"),
    ("file_rss", "  file mappings resident"),
    ("malloc_in_use_bytes", "glibc malloc: in use"),
    ("malloc_free_bytes", "glibc malloc: free, kept in arenas"),
    ("malloc_mmap_bytes", "glibc malloc: mmapped blocks"),
    ("sqlite_memory_used", "SQLite allocator (all connections)"),
    ("py_allocated_blocks", "Python: allocated blocks (count)"),
    ("gc_objects", "Python: gc-tracked objects (count)"),
    ("tracemalloc_bytes", "Python: tracemalloc bytes"),
]


@contextmanager
def probed_server(
    database_url: str, workdir: Path, label: str, source: Path | None, tracemalloc: bool,
    ready_timeout_s: float,
) -> Iterator[tuple[Server, Path]]:
    api_key = secrets.token_urlsafe(24)
    probe_out = workdir / f"probe-{label.replace(' ', '-')}.json"
    env = dict(os.environ)
    env |= {"FLEETHEALTH_DATABASE_URL": database_url, "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": api_key,
            PROBE_OUT_ENV: str(probe_out), PROBE_TRACE_ENV: "1" if tracemalloc else "0"}
    src = source or ROOT
    env["PYTHONPATH"] = f"{src}{os.pathsep}{src / 'clients' / 'python'}"
    migrate = subprocess.run([sys.executable, "-m", "app.cli", "migrate"], env=env, cwd=workdir,
                             capture_output=True, text=True, timeout=300)
    if migrate.returncode != 0:
        raise SystemExit(f"fleethealth migrate failed:\n{migrate.stdout}\n{migrate.stderr}")
    port = free_port()
    log_path = workdir / f"server-{port}.log"
    log_file = open(log_path, "wb")  # noqa: SIM115 - closed in finally
    process = subprocess.Popen(
        [sys.executable, __file__, PROBE_FLAG, "serve", "--host", "127.0.0.1", "--port", str(port),
         "--log-level", "warning", "--no-access-log"],
        env=env, cwd=workdir, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True,
    )
    server = Server(f"http://127.0.0.1:{port}", api_key, process, log_path)
    try:
        _wait_ready(server, ready_timeout_s)
        yield server, probe_out
    finally:
        _stop(process)
        log_file.close()


def take_probe(server: Server, probe_out: Path, timeout_s: float = 120.0) -> dict:
    before = json.loads(probe_out.read_text())["n"] if probe_out.exists() else 0
    os.kill(server.process.pid, signal.SIGUSR1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if probe_out.exists():
            snap = json.loads(probe_out.read_text())
            if snap["n"] > before:
                snap["figures"]["rss"] = tree_rss_bytes(server.process.pid)
                return dict(snap)
        time.sleep(0.1)
    raise TimeoutError("the server's memory probe did not answer")


async def register(server: Server, tail: str, first: int, last: int, batch_samples: int,
                   concurrency: int) -> None:
    """Streams ``first`` .. ``last - 1``: each registered and fed one batch, applied (``?wait=``)."""
    async with AsyncFleetHealthClient(server.url, server.api_key, timeout=300.0,
                                      max_connections=concurrency) as client:
        gate = asyncio.Semaphore(concurrency)

        async def one(i: int) -> None:
            actuator_id = f"idle-{i:06d}"
            t_s, channels = make_stream(batch_samples, seed=10_000 + i, t0=1.7e9)
            async with gate:
                await client.create_actuator(tail, actuator_id, channels=["current", "voltage"])
                await client.post_batch(tail, actuator_id, f"idle-{i}", channels, t_s=t_s,
                                        fmt="arrow", wait_s=60.0)

        await asyncio.gather(*(one(i) for i in range(first, last)))


def unapplied(server: Server, tail: str, n: int) -> int:
    """Streams of ``tail`` whose batch is not applied (read once, after the last probe)."""
    with FleetHealthClient(server.url, server.api_key, timeout=300.0) as client:
        fleet = client.fleet_health(sort="tail")
    applied = [act.get("last_applied_seq") for aircraft in fleet["aircraft"]
               if aircraft["tail"] == tail for act in aircraft["actuators"]]
    return n - sum(1 for s in applied if s is not None and s >= 1)


def run_one(label: str, database_url: str, workdir: Path, args: argparse.Namespace,
            source: Path | None) -> dict:
    run_id = secrets.token_hex(3).upper()
    steps: list[dict] = []
    with probed_server(database_url, workdir, label, source, args.tracemalloc,
                       args.ready_timeout_s) as (server, probe_out):
        print(f"[{label}] server pid {server.process.pid} ready", flush=True)
        with FleetHealthClient(server.url, server.api_key, timeout=120.0) as client:
            warm, tail = f"MW-{run_id}", f"MI-{run_id}"
            client.create_aircraft(warm)
            client.create_actuator(warm, "warm", channels=["current", "voltage"])
            t_s, channels = make_stream(10_000, seed=0, t0=1.7e9)
            client.post_batch(warm, "warm", "warm-0", channels, t_s=t_s, fmt="arrow", wait_s=60.0)
            client.create_aircraft(tail)
        live = [0]

        def settle_and_probe() -> dict:
            # Idle streams among a live one: after --settle-s (longer than the actuator look-up
            # cache's TTL), one batch on the warm stream, as any live traffic would send.
            time.sleep(args.settle_s)
            if args.live_post:
                live[0] += 1
                t, ch = make_stream(100, seed=live[0], t0=1.7e9 + 10.0 * live[0])
                with FleetHealthClient(server.url, server.api_key, timeout=120.0) as c:
                    c.post_batch(warm, "warm", f"live-{live[0]}", ch, t_s=t, fmt="arrow", wait_s=60.0)
            return take_probe(server, probe_out)

        steps.append({"streams": 0} | settle_and_probe())
        done = 0
        for size in args.steps:
            t0 = time.perf_counter()
            asyncio.run(register(server, tail, done, size, args.batch_samples, args.concurrency))
            took = time.perf_counter() - t0
            done = size
            snap = {"streams": size, "register_s": took} | settle_and_probe()
            steps.append(snap)
            print(f"[{label}] {size} streams ({took:.0f} s): RSS "
                  f"{snap['figures']['rss'] / 2**20:.1f} MiB", flush=True)
        missing = unapplied(server, tail, done)
    return {"steps": steps, "unapplied": missing}


def slope(steps: list[dict], key: str) -> float | None:
    """Least-squares bytes per stream over the steps with streams (the warmed server excluded)."""
    pts = [(s["streams"], s["figures"][key]) for s in steps if s["streams"] > 0 and key in s["figures"]]
    if len(pts) < 2:
        return None
    x, y = np.array(pts, dtype=float).T
    return float(np.polyfit(x, y, 1)[0])


def print_results(results: dict[str, dict]) -> None:
    labels = list(results)
    width = 18
    print()
    print("Server memory per idle registered stream: least-squares slope over "
          + ", ".join(str(s["streams"]) for s in next(iter(results.values()))["steps"][1:])
          + " streams (bytes/stream; counts per stream)")
    print(f"{'figure':<40}" + "".join(f"{lab:>{width}}" for lab in labels))
    for key, text in SLOPE_ROWS:
        vals = [slope(results[lab]["steps"], key) for lab in labels]
        if all(v is None for v in vals):
            continue
        print(f"{text:<40}" + "".join(f"{'-' if v is None else f'{v:,.1f}':>{width}}" for v in vals))
    # The server alone: a child process alive at one probe (none is expected) would blur it.
    first = [(r["steps"][1]["figures"]["rss_self"] - r["steps"][0]["figures"]["rss_self"])
             / r["steps"][1]["streams"] for r in results.values()]
    print(f"{'RSS (alone) delta, warmed -> 1st step':<40}" + "".join(f"{v:>{width},.1f}" for v in first))
    print(f"{'streams not applied (should be 0)':<40}"
          + "".join(f"{results[lab]['unapplied']:>{width}}" for lab in labels))
    print(f"goal: <= {GOAL_BYTES_PER_IDLE_STREAM:,} bytes per idle stream (RSS slope)")
    for lab in labels:
        print()
        print(f"{lab}: per step")
        cols = ("rss", "anonymous", "malloc_in_use_bytes", "malloc_free_bytes", "malloc_arenas",
                "sqlite_memory_used", "gc_objects", "threads")
        print(f"{'streams':>8}" + "".join(f"{c:>21}" for c in cols))
        for step in results[lab]["steps"]:
            f = step["figures"]
            cells = "".join(f"{'-' if c not in f else (f'{f[c] / 2**20:,.1f} MiB' if f[c] > 10**6 and c not in ('gc_objects',) else f'{f[c]:,}'):>21}"
                            for c in cols)
            print(f"{step['streams']:>8}{cells}")
        last = results[lab]["steps"][-1]
        print("  per-stream structures at the last step: "
              + "; ".join(f"{k} {v}" for k, v in last["structures"].items()))
        if "tracemalloc_top" in last:
            print("  tracemalloc top lines at the last step:")
            for line, size in last["tracemalloc_top"].items():
                print(f"    {size / 1024:10,.1f} KiB  {line}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pg", default=None, help="also run against this PostgreSQL URL")
    parser.add_argument("--no-sqlite", action="store_true", help="skip the SQLite run")
    parser.add_argument("--steps", type=int, nargs="+", default=[1000, 5000, 10000, 20000],
                        help="total registered streams after each step")
    parser.add_argument("--batch-samples", type=int, default=100)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--settle-s", type=float, default=35.0,
                        help="idle time before each probe (default: past the 30 s actuator cache TTL)")
    parser.add_argument("--live-post", action=argparse.BooleanOptionalAction, default=True,
                        help="one batch on the warm stream before each probe (live traffic)")
    parser.add_argument("--tracemalloc", action="store_true", help="trace Python allocations too")
    parser.add_argument("--ready-timeout-s", type=float, default=180.0)
    parser.add_argument("--json-out", type=Path, default=None)
    parser.add_argument("--baseline", type=Path, default=None,
                        help="also run against this source tree, at the same time, side by side")
    args = parser.parse_args(argv)
    args.steps = sorted(set(args.steps))
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="fleethealth-streammem-") as tmp:
        workdir = Path(tmp)
        trees: list[tuple[str, Path | None]] = [("", None)]
        if args.baseline is not None:
            trees = [(" base", args.baseline.resolve()), (" new", None)]

        def runs(suffix: str, source: Path | None) -> None:
            if not args.no_sqlite:
                url = f"sqlite:///{workdir / f'mem{suffix.strip()}.db'}"
                results[f"sqlite{suffix}"] = run_one(f"sqlite{suffix}", url, workdir, args, source)
            if args.pg:
                results[f"postgres{suffix}"] = run_one(f"postgres{suffix}", args.pg, workdir, args, source)

        threads = [threading.Thread(target=runs, args=t) for t in trees]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        order = [f"{b}{s}" for b in ("sqlite", "postgres") for s, _ in trees]
        results = {k: results[k] for k in order if k in results}
    if not results:
        return 1
    print_results(results)
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
