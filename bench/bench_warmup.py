"""Kernel warm-up: compile time per estimator kind, and the server's ways of warming up.

Part ``kinds``: for each estimator kind, in a fresh process with a fresh numba cache, the time to
import it and to compile its kernels (wall and CPU), then, in another fresh process, the time to
load them from the cache just filled.

Part ``modes``: ``app.kernels.KernelWarmup`` on a fresh cache, compiling in the server's thread
(``processes=0``) or in 2 child processes: when each kind is ready, and how late a 10 ms
timer thread in the server wakes up meanwhile (the interpreter lock a compile in the server
holds is what requests wait for), and how long ``stop()`` takes in the middle of it.

    .venv/bin/python bench/bench_warmup.py                # both parts
    .venv/bin/python bench/bench_warmup.py --part kinds
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

KINDS = ("fakf", "deterioration_ekf", "stmmae", "darr_fekf")
#: Child processes of the compared warm-ups (0: in the server's thread).
MODES = (0, 2)

_MEASURE = textwrap.dedent(
    """
    import importlib, json, sys, time
    t0 = time.perf_counter()
    mod = importlib.import_module("estimators." + sys.argv[1])
    t1 = time.perf_counter()
    c1 = time.process_time()
    mod.warm_up()
    print(json.dumps({"import_s": t1 - t0, "wall_s": time.perf_counter() - t1,
                      "cpu_s": time.process_time() - c1}))
    """
)


def _child(kind: str, cache: Path) -> dict[str, float]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    out = subprocess.run([sys.executable, "-c", _MEASURE, kind], env=env, capture_output=True,
                         text=True, check=True)
    result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def part_kinds() -> None:
    print("compile per kind (fresh process, fresh numba cache), then load from that cache")
    print(f"{'kind':<18} {'import s':>9} {'cold wall s':>12} {'cold CPU s':>11} {'cached wall s':>14} {'cached CPU s':>13}")
    totals = [0.0, 0.0]
    for kind in KINDS:
        with tempfile.TemporaryDirectory() as cache:
            cold = _child(kind, Path(cache))
            warm = _child(kind, Path(cache))
        totals[0] += cold["cpu_s"]
        totals[1] += warm["cpu_s"]
        print(f"{kind:<18} {cold['import_s']:9.2f} {cold['wall_s']:12.2f} {cold['cpu_s']:11.2f} "
              f"{warm['wall_s']:14.2f} {warm['cpu_s']:13.2f}")
    print(f"{'all kinds':<18} {'':>9} {'':>12} {totals[0]:11.2f} {'':>14} {totals[1]:13.2f}")


class _Lateness:
    """A thread that sleeps 10 ms at a time and records how late it wakes."""

    def __init__(self) -> None:
        self.late: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            t = time.perf_counter()
            time.sleep(0.01)
            self.late.append(time.perf_counter() - t - 0.01)

    def stop(self) -> dict[str, float]:
        self._stop.set()
        self._thread.join()
        late = sorted(self.late) or [0.0]
        return {"p50_ms": 1e3 * late[len(late) // 2], "p99_ms": 1e3 * late[int(0.99 * (len(late) - 1))],
                "max_ms": 1e3 * late[-1]}


_MODE = textwrap.dedent(
    """
    import json, sys, time
    sys.path.insert(0, sys.argv[3])
    from bench.bench_warmup import run_mode
    print(json.dumps(run_mode(int(sys.argv[1]), sys.argv[2] == "stop", sys.argv[4].split(","))), flush=True)
    import os
    os._exit(0)  # a compile stopped in a thread is still running: do not wait for it
    """
)


def run_mode(processes: int, stop_early: bool, kinds: list[str]) -> dict[str, Any]:
    """One warm-up in this process (a fresh one, with NUMBA_CACHE_DIR set by the caller)."""
    from app.kernels import KernelWarmup

    lateness = _Lateness()
    t0 = time.monotonic()
    ready: dict[str, float] = {}
    kernels = KernelWarmup(kinds, processes=processes,
                           on_ready=lambda kind: ready.setdefault(kind, time.monotonic() - t0))
    kernels.start()
    out: dict[str, Any] = {}
    if stop_early:
        while not any(s["status"] == "compiling" for s in kernels.snapshot().values()):
            time.sleep(0.05)
        time.sleep(2.0)
        t_stop = time.monotonic()
        kernels.stop()
        out["stop_s"] = time.monotonic() - t_stop
    else:
        kernels.done.wait()
    out["ready"] = ready
    out["all_s"] = time.monotonic() - t0
    out["lateness"] = lateness.stop()
    return out


def part_modes(kinds: list[str]) -> None:
    root = str(Path(__file__).resolve().parents[1])
    print("\nserver warm-up on a fresh numba cache: thread in the server vs child processes")
    print(f"{'mode':<12} " + " ".join(f"{k:>18}" for k in kinds) + f" {'all s':>7} {'timer late p50/p99/max ms':>26}")
    for processes in MODES:
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache}
            out = subprocess.run([sys.executable, "-c", _MODE, str(processes), "run", root, ",".join(kinds)],
                                 env=env,
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
        name = "thread" if processes == 0 else f"{processes} child" + ("ren" if processes > 1 else "")
        late = r["lateness"]
        print(f"{name:<12} " + " ".join(f"{r['ready'].get(k, float('nan')):18.1f}" for k in kinds)
              + f" {r['all_s']:7.1f} {late['p50_ms']:8.1f}/{late['p99_ms']:.1f}/{late['max_ms']:.1f}")
    print("\nstop() 2 s into the first compile (fresh cache)")
    for processes in (0, 2):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache}
            out = subprocess.run([sys.executable, "-c", _MODE, str(processes), "stop", root, ",".join(kinds)],
                                 env=env,
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
        name = "thread" if processes == 0 else f"{processes} children"
        print(f"{name:<12} stop() returned after {r['stop_s']:.2f} s"
              + (" (the compile goes on in the thread until the process exits)" if processes == 0 else ""))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--part", choices=("kinds", "modes", "all"), default="all")
    p.add_argument("--kinds", default=",".join(KINDS), help="kinds of the modes part (comma-separated)")
    args = p.parse_args()
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    if args.part in ("kinds", "all"):
        part_kinds()
    if args.part in ("modes", "all"):
        part_modes(args.kinds.split(","))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
