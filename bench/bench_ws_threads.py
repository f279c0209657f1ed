"""Where a WebSocket frame's server CPU goes: many connections, CPU per frame by thread.

One ``fleethealth serve`` (SQLite in a temporary folder, FAKF attached) per run; ``--streams``
connections (default 1,000) each send ``--frames`` 10-sample Arrow frames with the lean clients
of :mod:`bench_ws` (at most 4 awaiting their results). Printed per run: frames per second,
server and client CPU per frame, the CPU per frame of each server thread (``/proc``; thread
names from ``py-spy dump`` when py-spy is installed, else thread ids), and how the work was
grouped: apply transactions and log commits during the run (``/metrics``), so the appends per
log commit and the streams per apply group can be read off.

``--env NAME=VALUE`` (repeatable) runs the server with that setting; ``--alternate
NAME=V1,V2`` runs each value in turn, ``--runs`` times, one server at a time, so that two
settings are compared on the same state of the machine. ``--tree DIR`` measures another
source tree (e.g. ``git archive <rev> | tar -x -C /tmp/base``); ``--alternate-tree DIR`` runs it
in turn with this checkout.

Usage::

    .venv/bin/python bench/bench_ws_threads.py --alternate FLEETHEALTH_PROCESSOR_COMPUTE_BUDGET_S=0.005,0.05 --runs 2
    .venv/bin/python bench/bench_ws_threads.py --alternate-tree /tmp/base --runs 3

Figures are printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_ws  # noqa: E402
from bench_ingest import _tree, make_stream, running_server  # noqa: E402
from fleethealth_client import frames_of  # noqa: E402

_METRICS = ("fleethealth_apply_groups_total", "fleethealth_batches_applied_total",
            "fleethealth_log_group_appends_count", "fleethealth_log_group_appends_sum")


def _thread_cpu(pids: list[int]) -> dict[tuple[int, int], float]:
    """CPU seconds of every thread of the processes, by (pid, tid)."""
    out = {}
    tick = os.sysconf("SC_CLK_TCK")
    for pid in pids:
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out[(pid, int(tid))] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _thread_names(pids: list[int]) -> dict[int, str]:
    """Python thread names by native thread id, from ``py-spy dump`` (empty without py-spy)."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not Path(spy).exists():
        return {}
    names: dict[int, str] = {}
    for pid in pids:
        try:
            dump = subprocess.run([spy, "dump", "--nonblocking", "--json", "-p", str(pid)], capture_output=True,
                                  text=True, timeout=30).stdout
            for th in json.loads(dump):
                names[int(th["os_thread_id"])] = f"{'apply process' if pid != pids[0] else 'serve'}: {th['thread_name']}"
        except (OSError, ValueError, KeyError, subprocess.TimeoutExpired):
            continue
    return names


def _metrics(url: str, key: str) -> dict[str, float]:
    import httpx

    text = httpx.get(url + "/metrics", headers={"Authorization": f"Bearer {key}"}, timeout=30).text
    out: dict[str, float] = {}
    for line in text.splitlines():
        m = re.match(r"^(\w+)(\{[^}]*\})? ([0-9.eE+-]+)$", line)
        if m and m.group(1) in _METRICS:
            out[m.group(1)] = out.get(m.group(1), 0.0) + float(m.group(3))
    return out


def one_run(args: argparse.Namespace, env: dict[str, str], tree: Path | None) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="fleethealth-ws-threads-") as tmp, running_server(
        f"sqlite:///{Path(tmp) / 'ws.db'}", Path(tmp), 600.0, source=tree, extra_env=env
    ) as server:
        bench_ws._setup(server.url, server.api_key, "T", args.streams)
        t, chans = make_stream(10 * args.frames, seed=10, t0=0.0)
        frames = frames_of(t, chans, 10)
        pids = _tree(server.process.pid)
        m0, c0 = _metrics(server.url, server.api_key), _thread_cpu(pids)
        wall, client_cpu, server_cpu = bench_ws.many_connections(
            server.url, server.api_key, "T", args.streams, frames, args.client_procs, 4, server.process.pid)
        c1, m1 = _thread_cpu(pids), _metrics(server.url, server.api_key)
        names = _thread_names(pids)  # after the run: the parse pool's threads start with the first frames
    n = args.streams * len(frames)
    out = {"frames/s": n / wall, "server CPU ms/frame": 1e3 * server_cpu / n, "client CPU ms/frame": 1e3 * client_cpu / n}
    d = {k: m1.get(k, 0.0) - m0.get(k, 0.0) for k in _METRICS}
    out["apply groups"] = d["fleethealth_apply_groups_total"]
    out["batches per apply group"] = d["fleethealth_batches_applied_total"] / max(1.0, d["fleethealth_apply_groups_total"])
    out["log commits"] = d["fleethealth_log_group_appends_count"]
    out["appends per log commit"] = d["fleethealth_log_group_appends_sum"] / max(1.0, d["fleethealth_log_group_appends_count"])
    spent = sorted(((c1[k] - c0.get(k, 0.0), k) for k in c1), reverse=True)
    for cpu, (_, tid) in spent[: args.threads]:
        out[f"  {names.get(tid, f'thread {tid}')} ms/frame"] = 1e3 * cpu / n
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, default=1000)
    ap.add_argument("--frames", type=int, default=40, help="10-sample frames per connection")
    ap.add_argument("--client-procs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=8, help="threads listed, the busiest first")
    ap.add_argument("--env", action="append", default=[], help="NAME=VALUE for the server (repeatable)")
    ap.add_argument("--alternate", help="NAME=V1,V2,...: each value in turn")
    ap.add_argument("--tree", type=Path, help="measure this source tree instead of this checkout")
    ap.add_argument("--alternate-tree", type=Path, help="this source tree and this checkout in turn")
    ap.add_argument("--runs", type=int, default=1)
    args = ap.parse_args(argv)
    env = dict(kv.split("=", 1) for kv in args.env)
    variants: list[tuple[str, dict[str, str], Path | None]] = []
    if args.alternate:
        name, values = args.alternate.split("=", 1)
        variants = [(f"{name}={v}", {**env, name: v}, args.tree) for v in values.split(",")]
    elif args.alternate_tree:
        variants = [(f"tree {args.alternate_tree}", env, args.alternate_tree.resolve()), ("this checkout", env, None)]
    else:
        variants = [("this checkout" if args.tree is None else f"tree {args.tree}", env, args.tree)]
    for k in range(args.runs):
        for label, venv, tree in variants:
            out = one_run(args, venv, tree)
            print(f"run {k + 1}, {label}: {args.streams} connections x {args.frames} frames", flush=True)
            for key, value in out.items():
                print(f"  {key:<58} {value:12,.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
