"""Regenerate the dashboard screenshots in docs/img/ (``make screenshots``).

Starts ``fleethealth serve`` on a free loopback port with a fresh SQLite file, feeds it the
showcase fleet (every actuator kind, surface faults, a wearing drive, an SHA/EMA fault) through
the simulator, then takes the board and one page per kind in Debian's Chromium.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from fleethealth_client import FleetHealthClient
from playwright.sync_api import sync_playwright

from fleethealth_tools.showcase import SHA_EMA_ACTUATOR, feed_showcase_fleet

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "img"
KEY = "screenshots-admin-key-0123456789abcdef"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
PAGES = {
    "ema_voltage": "FH-001/ema-left",
    "friction_drive": "FH-002/taxi-drive",
    "flight_controls": "FH-002/flight-controls",
    "sha_ema": f"FH-001/{SHA_EMA_ACTUATOR}",
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(db: Path, log: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    env = {**os.environ, "FLEETHEALTH_DATABASE_URL": f"sqlite:///{db}", "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": KEY}
    fleethealth = str(Path(sys.executable).parent / "fleethealth")
    subprocess.run([fleethealth, "migrate"], env=env, check=True, capture_output=True)
    proc = subprocess.Popen(
        [fleethealth, "serve", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
        env=env, stdout=log.open("ab"), stderr=subprocess.STDOUT, cwd=ROOT,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 900.0  # a cold numba cache compiles for minutes
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server exited with {proc.returncode}; see {log}")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return proc, url
        time.sleep(0.5)
    proc.terminate()
    raise SystemExit(f"server not ready; see {log}")


def _wait_applied(url: str) -> None:
    with FleetHealthClient(url, KEY, timeout=60.0) as client:
        for ac in client.fleet_health()["aircraft"]:
            for act in ac["actuators"]:
                client.wait_applied(ac["tail"], act["actuator_id"], act["last_logged_seq"], timeout_s=900.0)


def _shoot(url: str, out: Path) -> list[Path]:
    written: list[Path] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 860})
        page.goto(f"{url}/")
        page.fill("#key", KEY)
        page.click("#login button[type=submit]")
        page.wait_for_selector("body[data-ready=true]", timeout=120_000)
        page.wait_for_selector("#live.on", timeout=60_000)
        shots = [("board", "")] + [(kind, f"#/a/{path}") for kind, path in PAGES.items()]
        for name, fragment in shots:
            if fragment:
                page.goto(f"{url}/{fragment}")
                page.wait_for_selector("body[data-ready=true]", timeout=120_000)
            page.wait_for_timeout(300)  # let the last canvas paint
            path = out / f"dashboard-{name}.png"
            page.screenshot(path=str(path), full_page=True)
            written.append(path)
        browser.close()
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=OUT)
    # 140 s: the seed paper's third surface fault (rudder stuck, 130-160 s) is active at the end.
    parser.add_argument("--duration-s", type=float, default=140.0, help="stream seconds simulated (140)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        proc, url = _serve(Path(tmp) / "screens.db", Path(tmp) / "server.log")
        try:
            feed_showcase_fleet(url, KEY, duration_s=args.duration_s, log=lambda line: print(line, flush=True))
            _wait_applied(url)
            for path in _shoot(url, args.out):
                print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
