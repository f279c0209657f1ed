"""Plot series on long histories: downsampling, the ``.../series`` endpoint, and drawing.

What is measured, for one FAKF stream of N samples (default 1,000,000 at 100 Hz, fed to a real
``fleethealth serve`` on 127.0.0.1 with a fresh SQLite file):

* ``min_max_downsample`` alone on N samples (1 and 4 series) to 1,200 points, best of 5;
* ``GET .../series`` over the whole history (points=1200: the server reads and decodes every
  output block, downsamples, answers JSON), best of 5, and a 1 % zoom;
* in Debian's Chromium (Playwright): fetching that answer and drawing it with uPlot (the clock
  stops at the first animation frame after the chart is built), best of 5; and, side by side,
  drawing all N samples sent raw (what a plot without server downsampling would face; the
  transfer of N samples as JSON is not even counted).

Usage::

    .venv/bin/python bench/bench_series.py              # N = 1,000,000
    .venv/bin/python bench/bench_series.py --samples 200000

Figures are printed; nothing is asserted.
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
import numpy as np
from fleethealth_client import FleetHealthClient
from playwright.sync_api import sync_playwright

from app.health.downsample import min_max_downsample

ROOT = Path(__file__).resolve().parents[1]
KEY = "bench-series-admin-key-0123456789"
POINTS = 1200
BATCH = 20_000
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
DRAW_JS = """async ({url, key, raw}) => {
  const t0 = performance.now();
  let data;
  if (raw) {  // n samples made in the page (a random walk), not timed as a transfer
    const x = new Float64Array(raw), y = new Float64Array(raw);
    for (let i = 0, v = 0; i < raw; i++) { x[i] = i / 100; v += Math.random() - 0.5; y[i] = v; }
    data = [x, y];
  } else {
    const r = await fetch(url, {headers: {Authorization: 'Bearer ' + key}});
    const j = await r.json();
    data = [j.t_s, j.series.voltage_estimate];
  }
  const t1 = performance.now();
  const el = document.createElement('div');
  document.body.append(el);
  const u = new uPlot({width: 1200, height: 300, series: [{}, {stroke: 'blue'}]}, data, el);
  await new Promise((ok) => requestAnimationFrame(() => ok()));
  const t2 = performance.now();
  u.destroy(); el.remove();
  return {fetch_ms: raw ? 0 : t1 - t0, draw_ms: t2 - t1, total_ms: raw ? t2 - t1 : t2 - t0, points: data[0].length};
}"""


def best(fn, repeat: int = 5) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def serve(db: Path) -> tuple[subprocess.Popen[bytes], str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "FLEETHEALTH_DATABASE_URL": f"sqlite:///{db}", "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": KEY}
    exe = str(Path(sys.executable).parent / "fleethealth")
    subprocess.run([exe, "migrate"], env=env, check=True, capture_output=True)
    proc = subprocess.Popen([exe, "serve", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 900
    while time.monotonic() < deadline:
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                return proc, url
        time.sleep(0.5)
    proc.terminate()
    raise SystemExit("server not ready")


def feed(url: str, n: int) -> None:
    rng = np.random.default_rng(0)
    t = np.arange(n) / 100.0
    current = np.sin(2 * np.pi * 0.3 * t) + 0.5 * np.sin(2 * np.pi * 1.7 * t) + 0.05 * rng.normal(size=n)
    voltage = np.zeros(n)
    for k in range(2, n):  # an ARX plant: the FAKF identifies it and tracks
        voltage[k] = 1.2 * voltage[k - 1] - 0.4 * voltage[k - 2] + 2.0 * current[k - 1]
    voltage += 0.1 * rng.normal(size=n)
    with FleetHealthClient(url, KEY, timeout=120.0) as c:
        c.create_aircraft("B1")
        c.create_actuator("B1", "ema", kind="ema_voltage")
        seq = 0
        for k in range(0, n, BATCH):
            s = slice(k, k + BATCH)
            seq = int(c.post_batch("B1", "ema", f"b{k}", {"current": current[s], "voltage": voltage[s]},
                                   t_s=t[s], fmt="arrow")["seq"])
        c.wait_applied("B1", "ema", seq, timeout_s=1800)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--samples", type=int, default=1_000_000)
    args = ap.parse_args()
    n = args.samples
    rng = np.random.default_rng(1)
    t = np.arange(n, dtype=np.float64) / 100.0
    ys = {f"y{i}": np.cumsum(rng.normal(size=n)) for i in range(4)}
    one = best(lambda: min_max_downsample(t, {"y0": ys["y0"]}, POINTS))
    four = best(lambda: min_max_downsample(t, ys, POINTS))
    print(f"min_max_downsample, {n:,} samples -> {POINTS} points: 1 series {one * 1e3:.1f} ms, "
          f"4 series {four * 1e3:.1f} ms")

    with tempfile.TemporaryDirectory() as tmp:
        proc, url = serve(Path(tmp) / "bench.db")
        try:
            t_feed = time.perf_counter()
            feed(url, n)
            print(f"fed and applied {n:,} samples in {time.perf_counter() - t_feed:.1f} s")
            path = f"{url}/v1/aircraft/B1/actuators/ema/series"
            q = {"estimator": "fakf", "names": "voltage_estimate", "points": POINTS}
            h = {"Authorization": f"Bearer {KEY}"}
            with httpx.Client(headers=h, timeout=120) as http:
                whole = http.get(path, params=q).json()
                t_whole = best(lambda: http.get(path, params=q).raise_for_status())
                lo, hi = n * 0.5 / 100.0, n * 0.51 / 100.0
                zq = {**q, "from_s": lo, "to_s": hi}
                zoom = http.get(path, params=zq).json()
                t_zoom = best(lambda: http.get(path, params=zq).raise_for_status())
                t_raw = best(lambda: http.get(f"{url}/v1/aircraft/B1/actuators/ema/outputs",
                                              params={"estimator": "fakf", "max_samples": n}).raise_for_status(), 1)
            print(f"GET series, whole history ({whole['n_samples']:,} samples -> {len(whole['t_s'])} points): "
                  f"{t_whole * 1e3:.0f} ms")
            print(f"GET series, 1 % zoom ({zoom['n_samples']:,} samples -> {len(zoom['t_s'])} points): "
                  f"{t_zoom * 1e3:.0f} ms")
            print(f"GET outputs, every sample (no downsampling, for comparison): {t_raw * 1e3:.0f} ms")
            with sync_playwright() as p:
                b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
                page = b.new_page()
                page.goto(f"{url}/")
                page.wait_for_function("() => !!window.uPlot")
                full_url = f"{path}?estimator=fakf&names=voltage_estimate&points={POINTS}"
                runs = [page.evaluate(DRAW_JS, {"url": full_url, "key": KEY, "raw": None}) for _ in range(5)]
                fast = min(runs, key=lambda r: r["total_ms"])
                slow = min((page.evaluate(DRAW_JS, {"url": "", "key": KEY, "raw": n}) for _ in range(3)),
                           key=lambda r: r["draw_ms"])
                b.close()
            print(f"browser, downsampled: fetch {fast['fetch_ms']:.0f} ms + draw {fast['draw_ms']:.0f} ms = "
                  f"{fast['total_ms']:.0f} ms for {fast['points']} points of {n:,} samples")
            print(f"browser, raw {slow['points']:,} samples (already in the page): draw {slow['draw_ms']:.0f} ms "
                  f"({slow['draw_ms'] / max(fast['draw_ms'], 1e-3):.0f}x the downsampled draw)")
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
