"""Time a first run of the demo: from ``fleethealth serve --demo`` to aircraft with data.

Starts ``fleethealth serve --demo`` in a fresh folder with a fresh numba cache (nothing compiled
yet, as on a new installation), and prints, from the start of the process:

* when each estimator kind's kernels became ready (``/readyz``),
* when the first, and the third, aircraft had applied data of this run (an actuator whose last
  applied sample is newer than the start), and when each demo kind first had some,
* how long the server took to exit after SIGTERM, and the size of the demo database.

Then it starts the same demo again (same folder, cache now warm: a second ``make demo``) and prints
the same figures. Run it on an otherwise idle machine for figures that mean something, e.g.::

    .venv/bin/python scripts/first_run.py             # cold start, then a second start
    .venv/bin/python scripts/first_run.py --runs 1    # the cold start only
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")
KEY = "first-run-demo-key-0123456789abcdef"
DEMO_KINDS = ("ema_voltage", "flight_controls", "friction_drive")
POLL_S = 0.5


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _get(url: str, **kw: Any) -> dict[str, Any] | None:
    try:
        r = httpx.get(url, timeout=5.0, **kw)
        body: dict[str, Any] = r.json()
        return body if r.status_code in (200, 503) else None
    except (httpx.HTTPError, ValueError):
        return None


def one_run(workdir: Path, cache_dir: Path, timeout_s: float) -> dict[str, Any]:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(cache_dir),
        "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": KEY,
    }
    env.pop("FLEETHEALTH_DATABASE_URL", None)
    log = open(workdir / "demo.log", "ab")  # noqa: SIM115 (closed below)
    start_epoch = time.time()
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [FLEETHEALTH, "serve", "--demo", "--port", str(port)],
        cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT,
    )
    figures: dict[str, Any] = {"kinds_ready": {}, "kind_data": {}}
    headers = {"Authorization": f"Bearer {KEY}"}
    try:
        while time.monotonic() - t0 < timeout_s and proc.poll() is None:
            now = time.monotonic() - t0
            ready = _get(f"{url}/readyz")
            if ready is not None:
                figures.setdefault("answering_s", now)
                for kind, k in (ready.get("kernels") or {}).items():
                    if k.get("status") == "ready":
                        figures["kinds_ready"].setdefault(kind, now)
            fleet = _get(f"{url}/v1/fleet/health", headers=headers)
            with_data = set()
            for aircraft in (fleet or {}).get("aircraft", []):
                for act in aircraft["actuators"]:
                    if (act.get("t_last_s") or 0.0) >= start_epoch:
                        with_data.add(aircraft["tail"])
                        figures["kind_data"].setdefault(act["kind"], now)
            if with_data:
                figures.setdefault("first_aircraft_s", now)
            if len(with_data) >= 3:
                figures.setdefault("three_aircraft_s", now)
            # Done once every demo kind has data, or 30 s after three aircraft have some (a
            # second start does not resume the taxi drives: their wear is not stored).
            if "three_aircraft_s" in figures and (
                all(k in figures["kind_data"] for k in DEMO_KINDS) or now - figures["three_aircraft_s"] > 30.0
            ):
                break
            time.sleep(POLL_S)
    finally:
        t_term = time.monotonic()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        figures["exit_after_sigterm_s"] = time.monotonic() - t_term
        figures["exit_code"] = proc.returncode
        log.close()
    db = workdir / "data" / "fleethealth.db"
    figures["db_bytes"] = sum(p.stat().st_size for p in db.parent.glob("fleethealth.db*")) if db.exists() else 0
    return figures


def show(name: str, f: dict[str, Any]) -> None:
    def s(value: float | None) -> str:
        return "never" if value is None else f"{value:6.1f} s"

    print(f"{name}:")
    print(f"  server answering        {s(f.get('answering_s'))}")
    for kind, t in sorted(f["kinds_ready"].items(), key=lambda kv: kv[1]):
        print(f"  kernels {kind:<17} {s(t)}")
    print(f"  first aircraft w/ data  {s(f.get('first_aircraft_s'))}")
    print(f"  3 aircraft with data    {s(f.get('three_aircraft_s'))}")
    for kind in DEMO_KINDS:
        print(f"  first {kind:<17} {s(f['kind_data'].get(kind))}")
    print(f"  exit after SIGTERM      {s(f['exit_after_sigterm_s'])} (code {f['exit_code']})")
    print(f"  demo database           {f['db_bytes'] / 1e6:6.1f} MB")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=2, help="1: cold start only; 2: cold, then warm (default)")
    p.add_argument("--timeout-s", type=float, default=900.0, help="limit per run (default 900)")
    p.add_argument("--keep", action="store_true", help="keep the work folder (its demo.log)")
    args = p.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="fleethealth-first-run-"))
    cache_dir = workdir / "numba-cache"
    print(f"work folder {workdir}; {os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f}")
    try:
        for run in range(args.runs):
            figures = one_run(workdir, cache_dir, args.timeout_s)
            show("first start (cold numba cache)" if run == 0 else f"start {run + 1} (warm cache)", figures)
            print(f"  load average now {os.getloadavg()[0]:.1f}", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
