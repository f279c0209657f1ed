"""Sustained load of large batch uploads against a real ``fleethealth serve`` on 127.0.0.1, then idle.

``--clients`` threads each post large batches (Arrow, CSV and JSON in turn, ``--samples`` samples of
2 channels each, times given by t0 and the sample rate, every client on its own actuator) one after the other for ``--duration``
seconds; then the server is left alone for ``--idle`` seconds. Every ``--every`` seconds the
server's resident memory (``VmRSS``, and its anonymous part ``RssAnon``) is printed with the
phase and the answers so far (202 logged, 503 budget busy, others). At the end: the idle RSS
before the load, the peak under load (``VmHWM``), and the RSS at the end of idle.

Usage::

    .venv/bin/python bench/soak/large_batches.py                  # 4 clients, 60 s, idle 30 s
    .venv/bin/python bench/soak/large_batches.py --clients 2 --duration 15 --idle 10   # quick
    .venv/bin/python bench/soak/large_batches.py --env FLEETHEALTH_INGEST_MEMORY_BYTES=268435456
    .venv/bin/python bench/soak/large_batches.py --source /tmp/base     # another source tree

Figures are printed; nothing is asserted. Requests are bounded by the duration and stop by
themselves; the server is stopped at the end.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

from bench_ingest import running_server  # noqa: E402
from fleethealth_client import FleetHealthClient, encode_batch  # noqa: E402

MB = 1e6
TAIL = "SOAKBIG"
FORMATS = ("arrow", "csv", "json")


def status_mb(pid: int) -> dict[str, float]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key = line.split(":")[0]
        if key in ("VmRSS", "VmHWM", "RssAnon"):
            out[key] = int(line.split()[1]) / 1024 * 1.048576
    return out


class Bodies:
    """The batch bodies, encoded once: times by ``t0`` + ``sample_rate_hz`` (query parameters for
    CSV and Arrow, fields of the JSON document), so that each request only sets its own t0."""

    def __init__(self, samples: int) -> None:
        import orjson

        rng = np.random.default_rng(11)
        channels = {"current": rng.normal(size=samples), "voltage": rng.normal(size=samples)}
        self.samples = samples
        self.tables = {}
        for fmt in ("arrow", "csv"):
            enc = encode_batch(fmt, "x", channels, t0=0.0, sample_rate_hz=1000.0)
            self.tables[fmt] = (enc.content, enc.content_type)
        self.json_channels = orjson.dumps(channels, option=orjson.OPT_SERIALIZE_NUMPY)

    def request(self, fmt: str, batch_id: str, t0: float) -> tuple[bytes, str, dict[str, str]]:
        if fmt == "json":
            head = f'{{"batch_id":"{batch_id}","t0":{t0!r},"sample_rate_hz":1000.0,"channels":'.encode()
            return head + self.json_channels + b"}", "application/json", {}
        content, ctype = self.tables[fmt]
        return content, ctype, {"batch_id": batch_id, "t0": repr(t0), "sample_rate_hz": "1000.0"}


def client_loop(url: str, key: str, actuator: str, made: Bodies, stop_at: float,
                answers: collections.Counter[str], lock: threading.Lock) -> None:
    path = f"{url}/v1/aircraft/{TAIL}/actuators/{actuator}/telemetry"
    k = 0
    with httpx.Client(timeout=300, headers={"Authorization": f"Bearer {key}"}) as http:
        while time.monotonic() < stop_at:
            fmt = FORMATS[k % len(FORMATS)]
            # Each batch after the last in time: its own t0.
            content, ctype, params = made.request(fmt, f"{actuator}-{k}", 1.7e9 + k * made.samples * 1e-3)
            try:
                r = http.post(path, content=content, params=params, headers={"Content-Type": ctype})
                label = str(r.status_code)
            except httpx.TransportError as exc:
                label = type(exc).__name__
            with lock:
                answers[label] += 1
            k += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per batch (t + 2 channels)")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--idle", type=float, default=30.0)
    ap.add_argument("--every", type=float, default=2.0, help="seconds between printed rows")
    ap.add_argument("--source", help="another source tree to serve (e.g. git worktree add --detach DIR main)")
    ap.add_argument("--env", action="append", default=[], metavar="FLEETHEALTH_X=VALUE")
    a = ap.parse_args()
    env = dict(e.split("=", 1) for e in a.env)
    with tempfile.TemporaryDirectory(prefix="fh-soak-big-") as tmp:
        work = Path(tmp)
        with running_server(f"sqlite:///{work / 'soak.db'}", work, 300.0,
                            source=Path(a.source) if a.source else None, extra_env=env) as server:
            pid = server.process.pid
            with FleetHealthClient(server.url, server.api_key) as c:
                c.create_aircraft(TAIL)
                for i in range(a.clients):
                    c.create_actuator(TAIL, f"c{i}", channels=["current", "voltage"])
            time.sleep(2.0)
            start = status_mb(pid)
            Path(f"/proc/{pid}/clear_refs").write_text("5")
            made = Bodies(a.samples)
            print(f"{a.clients} clients, batches of {a.samples:,} samples (body MB: "
                  + ", ".join(f"{f} {len(made.request(f, 'x', 0.0)[0]) / MB:.0f}" for f in FORMATS)
                  + f"), load {a.duration:g} s, idle {a.idle:g} s; settings {env or 'default'}; "
                  f"load average {os.getloadavg()[0]:.1f}")
            print(f"idle server before the load: RSS {start['VmRSS']:.0f} MB (anon {start['RssAnon']:.0f})")
            answers: collections.Counter[str] = collections.Counter()
            lock = threading.Lock()
            t0 = time.monotonic()
            stop_at = t0 + a.duration
            threads = [threading.Thread(target=client_loop, daemon=True,
                                        args=(server.url, server.api_key, f"c{i}", made, stop_at,
                                              answers, lock))
                       for i in range(a.clients)]
            for t in threads:
                t.start()
            print(f"{'t s':>6} {'phase':<6}{'RSS MB':>8}{'anon MB':>9}{'peak MB':>9}  answers")
            load_peak = 0.0
            end = stop_at + a.idle
            phase = "load"
            next_row = t0
            while True:
                now = time.monotonic()
                if phase == "load" and not any(t.is_alive() for t in threads):
                    phase = "idle"
                    load_peak = status_mb(pid)["VmHWM"]
                    end = now + a.idle
                if phase == "idle" and now >= end:
                    break
                if now >= next_row:
                    m = status_mb(pid)
                    with lock:
                        shown = ", ".join(f"{k} {v}" for k, v in sorted(answers.items()))
                    print(f"{now - t0:>6.1f} {phase:<6}{m['VmRSS']:>8.0f}{m['RssAnon']:>9.0f}"
                          f"{m['VmHWM']:>9.0f}  {shown}", flush=True)
                    next_row += a.every
                time.sleep(0.1)
            final = status_mb(pid)
            print(f"answers: {dict(answers)}")
            print(f"RSS before the load {start['VmRSS']:.0f} MB, peak under load {load_peak:.0f} MB "
                  f"(+{load_peak - start['VmRSS']:.0f}), at the end of idle {final['VmRSS']:.0f} MB "
                  f"(+{final['VmRSS'] - start['VmRSS']:.0f}; anon +{final['RssAnon'] - start['RssAnon']:.0f})")


if __name__ == "__main__":
    main()
