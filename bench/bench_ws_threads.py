"""Where a WebSocket frame's server CPU goes: many connections, CPU per frame by thread.

One ``fleethealth serve`` (SQLite in a temporary folder, FAKF attached) per run; ``--streams``
connections (default 1,000) each send ``--frames`` 10-sample Arrow frames with the lean clients
of :mod:`bench_ws` (at most 4 awaiting their results). Printed per run: frames per second,
server and client CPU per frame (``/proc``), the CPU per frame of the server's threads by name
(``fleethealth_thread_cpu_seconds_total``, the apply process's as ``apply:<thread>``), and how
the work was grouped: apply transactions, batches applied and log commits during the run
(``/metrics``), so the appends per log commit and the batches per apply group can be read off.

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
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_ws  # noqa: E402
from bench_ingest import Server, make_stream, metric_by_label, running_server  # noqa: E402
from fleethealth_client import frames_of  # noqa: E402

#: How often the apply process sends its metrics to ``serve`` (app/processing/apply_process.py),
#: plus a margin: waited before each reading so that the child's CPU is in it.
CHILD_REPORT_S = 1.5

_THREADS = "fleethealth_thread_cpu_seconds_total"
#: Counters read before and after the run: apply transactions (by path), batches applied, and
#: the log writer's commits (its group-size histogram's count and sum).
_COUNTERS = ("fleethealth_apply_groups_total", "fleethealth_batches_applied_total",
             "fleethealth_log_group_appends_count", "fleethealth_log_group_appends_sum")


def _snapshot(server: Server) -> dict[str, dict[str, float]]:
    """The counters above and the CPU seconds of the server's threads by name (``serve``'s and,
    as ``apply:<thread>``, its apply process's), from ``/metrics``."""
    return {name: metric_by_label(server, name, "path") for name in _COUNTERS} | {
        _THREADS: metric_by_label(server, _THREADS, "thread")}


def one_run(args: argparse.Namespace, env: dict[str, str], tree: Path | None) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="fleethealth-ws-threads-") as tmp, running_server(
        f"sqlite:///{Path(tmp) / 'ws.db'}", Path(tmp), 600.0, source=tree, extra_env=env
    ) as server:
        bench_ws._setup(server.url, server.api_key, "T", args.streams)
        t, chans = make_stream(10 * args.frames, seed=10, t0=0.0)
        frames = frames_of(t, chans, 10)
        before: dict[str, dict[str, float]] = {}

        def at_go() -> None:  # every connection open: the handshakes are not counted
            time.sleep(CHILD_REPORT_S)  # the apply process's metrics reach serve once a second
            before.update(_snapshot(server))

        wall, client_cpu, server_cpu = bench_ws.many_connections(
            server.url, server.api_key, "T", args.streams, frames, args.client_procs, 4, server.process.pid,
            at_go=at_go)
        time.sleep(CHILD_REPORT_S)
        after = _snapshot(server)
    n = args.streams * len(frames)

    def delta(name: str) -> dict[str, float]:
        return {k: v - before[name].get(k, 0.0) for k, v in after[name].items()}

    groups = sum(delta("fleethealth_apply_groups_total").values())
    commits = sum(delta("fleethealth_log_group_appends_count").values())
    out = {"frames/s": n / wall, "server CPU ms/frame": 1e3 * server_cpu / n, "client CPU ms/frame": 1e3 * client_cpu / n,
           "apply groups": groups,
           "batches per apply group": sum(delta("fleethealth_batches_applied_total").values()) / max(1.0, groups),
           "log commits": commits,
           "appends per log commit": sum(delta("fleethealth_log_group_appends_sum").values()) / max(1.0, commits)}
    # A pool thread that ended during the run takes its CPU out of the sum (app/system/threads.py):
    # the request pool's figure is a lower bound.
    for thread, cpu in sorted(delta(_THREADS).items(), key=lambda kv: -kv[1])[: args.threads]:
        out[f"  {thread} ms/frame"] = 1e3 * cpu / n
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
