"""In-process cost of parsing one small frame or REST body, for this tree and a baseline tree.

Measured per call, in thread CPU time (``time.thread_time``), on frames of 10 samples of two
channels (``current`` and ``voltage``, with a ``t`` column, built as ``bench/bench_ws.py`` builds
them, with the client library's ``encode_frame``):

* ``ws arrow`` / ``ws json``: :func:`app.telemetry.service.prepare_frame` on a binary (Arrow
  IPC) or text (JSON) WebSocket frame: decode, value checks, digest and log block;
* ``rest arrow`` / ``rest json``: the REST body path (``app.telemetry.service._parse_body``) on
  the same samples as a body.

Each tree is imported in its own worker process (the tree's own ``app`` package first on the
path); the workers run in turns, ``--rounds`` times, each turn ``--frames`` distinct frames per
case, so that both share whatever else loads the machine alike. The median of the rounds is
printed, side by side.

Usage::

    git -C . archive <commit> | tar -x -C /tmp/base
    .venv/bin/python bench/bench_parse.py --baseline /tmp/base

Figures are printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = 10
CASES = ("ws arrow", "ws json", "rest arrow", "rest json")


def _worker(root: Path, n_frames: int) -> None:
    """Import ``root``'s app, build the frames, then time a turn per line read from stdin."""
    sys.path.insert(0, str(root))
    sys.path.insert(1, str(ROOT / "clients" / "python"))  # the same client encodes both trees' frames
    import numpy as np
    from fleethealth_client import encode_frame

    import app
    from app.ingest import TimeParams
    from app.telemetry import service
    from app.telemetry.body import RequestBody
    from app.telemetry.validation import DEFAULT_LIMITS

    assert Path(app.__file__).resolve().is_relative_to(root.resolve()), app.__file__
    channels = ["current", "voltage"]
    rng = np.random.default_rng(20261203)
    frames: dict[str, list[Any]] = {c: [] for c in CASES}
    for i in range(n_frames):
        t = 1000.0 + (i * SAMPLES + np.arange(SAMPLES)) / 1000.0
        chans = {"current": rng.normal(0, 1, SAMPLES), "voltage": rng.normal(0, 10, SAMPLES)}
        frames["ws arrow"].append(encode_frame(i + 1, chans, t_s=t, binary=True))
        frames["ws json"].append(encode_frame(i + 1, chans, t_s=t))
        frames["rest arrow"].append(encode_frame(i + 1, chans, t_s=t, binary=True))
        body = {"batch_id": f"b{i}", "t": t.tolist(), "channels": {k: v.tolist() for k, v in chans.items()}}
        frames["rest json"].append(json.dumps(body).encode())

    def ws(data: Any) -> None:
        service.prepare_frame(data, channels, 100_000, DEFAULT_LIMITS)

    def rest(mt: str, batch_id: str | None) -> Any:
        # An Arrow body's batch id is a request parameter; a JSON body carries its own.
        params = TimeParams(batch_id, None, None)

        def run(data: bytes) -> None:
            body = RequestBody(bytearray(data), None, len(data))
            service._parse_body(body, mt, params, channels, 100_000, DEFAULT_LIMITS, None)
        return run

    calls = {"ws arrow": ws, "ws json": ws,
             "rest arrow": rest("application/vnd.apache.arrow.stream", "batch-1"),
             "rest json": rest("application/json", None)}
    for case in CASES:  # warm-up (caches, first-call costs)
        for data in frames[case][:50]:
            calls[case](data)
    print("ready", flush=True)
    for _ in sys.stdin:
        out = {}
        for case in CASES:
            fn = calls[case]
            c0 = time.thread_time()
            for data in frames[case]:
                fn(data)
            out[case] = (time.thread_time() - c0) / len(frames[case]) * 1e6
        print(json.dumps(out), flush=True)


def _start(root: Path, n_frames: int) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, __file__, "--worker", str(root), "--frames", str(n_frames)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(root))
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"worker for {root} did not start: {line!r}")
    return proc


def _turn(proc: subprocess.Popen[str]) -> dict[str, float]:
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    result: dict[str, float] = json.loads(proc.stdout.readline())
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", type=Path, help="a baseline tree to measure side by side")
    ap.add_argument("--frames", type=int, default=2000, help="distinct frames per case and turn")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        _worker(args.worker, args.frames)
        return 0
    trees = [("this tree", ROOT)] + ([("baseline", args.baseline)] if args.baseline else [])
    procs = [(label, _start(root, args.frames)) for label, root in trees]
    runs: dict[str, list[dict[str, float]]] = {label: [] for label, _ in trees}
    try:
        for _ in range(args.rounds):
            for label, proc in procs:
                runs[label].append(_turn(proc))
    finally:
        for _, proc in procs:
            assert proc.stdin is not None
            proc.stdin.close()
            proc.wait(30)

    def median(label: str, case: str) -> float:
        values = sorted(r[case] for r in runs[label])
        return values[len(values) // 2]

    print(f"Parse of a {SAMPLES}-sample frame of 2 channels and t, thread CPU us per call "
          f"(median of {args.rounds} turns of {args.frames} frames); load average "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    header = f"{'case':<12}" + "".join(f"{label:>12}" for label, _ in trees)
    if args.baseline:
        header += f"{'ratio':>8}"
    print(header)
    for case in CASES:
        row = f"{case:<12}" + "".join(f"{median(label, case):>12.1f}" for label, _ in trees)
        if args.baseline:
            row += f"{median('baseline', case) / median('this tree', case):>7.2f}x"
        print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
