"""Peak memory of taking in one large batch, against the batch's own size.

Two parts:

* in-process (default): each format runs in a fresh process: build the request body, note the
  peak RSS, then parse and validate it and encode it for the telemetry log exactly as the API
  does, and note the peak again. Prints the extra peak memory as a multiple of the float64 size
  of the samples (t + 2 channels).
* ``--server``: each case runs against a fresh ``fleethealth serve`` on 127.0.0.1 (SQLite in a
  temporary folder, no estimator attached, so only the ingest path is measured): a chunked upload
  without Content-Length past ``MAX_BODY_BYTES`` (refused with 413), then one accepted JSON, CSV
  and Arrow batch of about the same body size. For each: the server's resident memory before,
  its peak while the request is served (``VmHWM``, reset through ``/proc/PID/clear_refs`` just
  before the request), its RSS right after the answer and after ``--idle`` seconds. ``--base DIR``
  runs the same cases against another source tree (``git worktree add --detach DIR main``) in
  the same run, side by side.

    .venv/bin/python bench/bench_batch_memory.py [--samples 1000000]
    .venv/bin/python bench/bench_batch_memory.py --server [--server-samples 1350000] [--base DIR]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys


def child(fmt: str, n: int) -> None:
    import io

    import numpy as np
    import orjson
    import pyarrow as pa

    from app.codec import encode_columns
    from app.ingest import TimeParams, parse_body

    rng = np.random.default_rng(0)
    t = np.arange(n) * 1e-3
    cur, volt = rng.normal(size=n), rng.normal(size=n)
    if fmt == "json":
        body = orjson.dumps(
            {
                "batch_id": "m",
                "t": t.tolist(),
                "channels": {"current": cur.tolist(), "voltage": volt.tolist()},
            }
        )
        mt = "application/json"
    elif fmt == "csv":
        buf = io.StringIO()
        np.savetxt(
            buf,
            np.column_stack([t, cur, volt]),
            delimiter=",",
            header="t,current,voltage",
            comments="",
            fmt="%.17g",
        )
        body = buf.getvalue().encode()
        mt = "text/csv"
    else:
        table = pa.table({"t": t, "current": cur, "voltage": volt})
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as w:
            w.write_table(table)
        body = sink.getvalue().to_pybytes()
        mt = "application/vnd.apache.arrow.stream"
    del t, cur, volt
    import gc

    gc.collect()
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    parsed = parse_body(body, mt, TimeParams("m", None, None), ["current", "voltage"], 10_000_000)
    payload = encode_columns({"t": parsed.t_s, **parsed.channels})
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(
        json.dumps(
            {
                "fmt": fmt,
                "body": len(body),
                "samples_bytes": 24 * n,
                "extra_peak": peak - base,
                "payload": len(payload),
            }
        )
    )


# ----------------------------------------------------------------------------- against a server
MB = 1e6
CHANNELS = ["current", "voltage"]


def proc_status_bytes(pid: int, key: str) -> int:
    """A ``VmRSS`` / ``VmHWM`` line of ``/proc/PID/status``, in bytes."""
    from pathlib import Path

    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


def reset_peak(pid: int) -> None:
    """Reset the process's peak RSS (``VmHWM``) to its current RSS (Linux >= 4.0)."""
    from pathlib import Path

    Path(f"/proc/{pid}/clear_refs").write_text("5")


def server_bodies(n: int) -> dict[str, tuple[bytes, str, dict[str, str]]]:
    """JSON, CSV and Arrow bodies of ``n`` samples (t + 2 channels), as the client encodes them."""
    import numpy as np
    from fleethealth_client import encode_batch

    rng = np.random.default_rng(0)
    t_s = 1.7e9 + np.arange(n) * 1e-3
    channels = {"current": rng.normal(size=n), "voltage": rng.normal(size=n)}
    out = {}
    for fmt in ("json", "csv", "arrow"):
        enc = encode_batch(fmt, f"big-{fmt}", channels, t_s=t_s)
        out[fmt] = (enc.content, enc.content_type, dict(enc.params))
    return out


def chunked_body(total: int, chunk: int = 1 << 20):  # type: ignore[no-untyped-def]
    """A JSON-looking body sent without Content-Length (chunked transfer encoding)."""
    piece = b"1.2345678901234567," * (chunk // 19)
    sent = 0
    yield b'{"batch_id": "chunked", "t0": 0, "sample_rate_hz": 1000, "channels": {"current": ['
    while sent < total:
        yield piece
        sent += len(piece)


def server_case(case: str, body: tuple[bytes, str, dict[str, str]] | None, chunked_mb: int,
                idle_s: float, source: str | None, env: dict[str, str]) -> dict[str, float | str | int]:
    import tempfile
    import time
    from pathlib import Path

    import httpx
    from bench_ingest import running_server
    from fleethealth_client import FleetHealthClient

    with tempfile.TemporaryDirectory(prefix="fh-batchmem-") as tmp:
        work = Path(tmp)
        url = f"sqlite:///{work / 'fh.db'}"
        with running_server(url, work, 300.0, source=Path(source) if source else None,
                            extra_env=env) as server:
            pid = server.process.pid
            with FleetHealthClient(server.url, server.api_key) as client:
                client.create_aircraft("MEM")
                client.create_actuator("MEM", "a1", channels=CHANNELS)
            time.sleep(1.0)
            before = proc_status_bytes(pid, "VmRSS")
            reset_peak(pid)
            path = f"{server.url}/v1/aircraft/MEM/actuators/a1/telemetry"
            auth = {"Authorization": f"Bearer {server.api_key}"}
            sent = 0
            with httpx.Client(timeout=300) as http:
                if body is None:
                    try:
                        status = http.post(path, content=chunked_body(chunked_mb << 20),
                                           headers={**auth, "Content-Type": "application/json"}).status_code
                    except httpx.TransportError as exc:  # the server closed mid-upload
                        status = f"closed ({type(exc).__name__})"  # type: ignore[assignment]
                    sent = chunked_mb << 20
                else:
                    content, ctype, params = body
                    sent = len(content)
                    status = http.post(path, content=content, params=params,
                                       headers={**auth, "Content-Type": ctype}).status_code
            peak = proc_status_bytes(pid, "VmHWM")
            after = proc_status_bytes(pid, "VmRSS")
            time.sleep(idle_s)
            idle = proc_status_bytes(pid, "VmRSS")
    return {"case": case, "status": status, "body": sent, "before": before, "peak": peak,
            "after": after, "idle": idle}


def run_server(a: argparse.Namespace) -> None:
    import os

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    bodies = server_bodies(a.server_samples)
    sources: list[tuple[str, str | None]] = [("this tree", None)]
    if a.base:
        sources.insert(0, (f"base {a.base}", a.base))
    print(f"cases: chunked upload of {a.chunked_mb} MiB without Content-Length (default limit "
          f"256 MiB), and batches of {a.server_samples:,} samples (t + 2 channels, "
          f"{24 * a.server_samples / MB:.0f} MB as float64); idle {a.idle:g} s; load {os.getloadavg()}")
    print(f"{'code':<26}{'case':<16}{'status':>8}{'body MB':>9}{'RSS MB':>8}{'peak MB':>9}"
          f"{'+peak':>7}{'x body':>7}{'after':>7}{'idle':>7}")
    env = dict(e.split("=", 1) for e in a.env)
    for label, source in sources:
        for case in a.cases.split(","):
            body = None if case == "chunked-reject" else bodies[case]
            r = server_case(case, body, a.chunked_mb, a.idle, source, env)
            extra = float(r["peak"]) - float(r["before"])
            print(f"{label[-26:]:<26}{case:<16}{r['status']!s:>8}{float(r['body']) / MB:>9.1f}"
                  f"{float(r['before']) / MB:>8.0f}{float(r['peak']) / MB:>9.0f}{extra / MB:>7.0f}"
                  f"{extra / float(r['body']):>7.2f}{(float(r['after']) - float(r['before'])) / MB:>+7.0f}"
                  f"{(float(r['idle']) - float(r['before'])) / MB:>+7.0f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--child", choices=["json", "csv", "arrow"])
    ap.add_argument("--server", action="store_true", help="measure a real server process")
    ap.add_argument("--server-samples", type=int, default=1_350_000)
    ap.add_argument("--chunked-mb", type=int, default=300)
    ap.add_argument("--idle", type=float, default=10.0)
    ap.add_argument("--base", help="another source tree to measure side by side (server cases)")
    ap.add_argument("--cases", default="chunked-reject,json,csv,arrow")
    ap.add_argument("--env", action="append", default=[], metavar="FLEETHEALTH_X=VALUE",
                    help="extra server setting (repeatable)")
    a = ap.parse_args()
    if a.server:
        run_server(a)
        return
    if a.child:
        child(a.child, a.samples)
        return
    print(
        f"one batch of {a.samples:,} samples (t + 2 channels, float64 = {24 * a.samples / 1e6:.0f} MB)"
    )
    print(
        f"{'format':<7}{'body MB':>9}{'extra peak MB':>15}{'x samples':>11}{'x body':>8}{'log MB':>8}"
    )
    for fmt in ("arrow", "csv", "json"):
        out = subprocess.run(
            [sys.executable, __file__, "--child", fmt, "--samples", str(a.samples)],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout)
        print(
            f"{fmt:<7}{r['body'] / 1e6:>9.1f}{r['extra_peak'] / 1e6:>15.1f}"
            f"{r['extra_peak'] / r['samples_bytes']:>11.2f}{r['extra_peak'] / r['body']:>8.2f}{r['payload'] / 1e6:>8.1f}"
        )


if __name__ == "__main__":
    main()
