"""``fleethealth replay``: send recorded runs to a running server.

Accepted files:

* NASA FLEA runs (``*.data.gz`` or ``*.data``): the driven motor's current and voltage, read by
  :func:`estimators.flea.read_flea_run`, sent as channels ``current`` and ``voltage`` with absolute
  times ``t0_epoch_s + t_s``.
* Any CSV file with a header row and a ``t`` column (seconds; POSIX seconds recommended): the other
  columns are the channels, empty cells are missing samples. ``--t-offset-s`` is added to ``t``.

Streams: without ``--actuator`` each file becomes its own actuator, named from the file (a FLEA
run ``BatchProfile_sine11_2010_09_03_09_51_40_Nominal_Low`` becomes
``flea-sine11-nominal-20100903-095140``), so that each run gets its own FAKF identification and
health indicators. With ``--actuator NAME`` every file goes into that one actuator, in order of their
first time stamp, forming one increasing stream.

Batch ids are derived from the file name and the sample offset, so running the same replay twice
sends nothing new: the server answers the repeats with its first answers.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from fleethealth_client import BATCH_FORMATS, ApiError, FleetHealthClient

from fleethealth_tools.readiness import wait_for_server

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TAIL = "FLEA-STAND"
ACTUATOR_KIND = "ema_voltage"
_FLEA_NAME = re.compile(
    r"^BatchProfile_(?P<profile>[a-z]+\d+(?:-2m)?)_(?P<date>\d{4}_\d{2}_\d{2})_"
    r"(?P<clock>\d{2}_\d{2}_\d{2})_(?P<scenario>[A-Za-z]+)_Low$"
)


@dataclass(frozen=True)
class Recording:
    """One file's samples, ready to send.

    Attributes:
        path: the file.
        name: file name without its data suffixes.
        t_s: absolute sample times, seconds, strictly increasing.
        channels: channel name -> float64 values (NaN = missing).
        actuator_id: actuator this file goes to when no ``--actuator`` is given.
        description: one line for the log.
    """

    path: Path
    name: str
    t_s: np.ndarray
    channels: dict[str, np.ndarray]
    actuator_id: str
    description: str

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def _slug(text: str, max_len: int = 64) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return slug[:max_len].rstrip("-") or "run"


def flea_actuator_id(name: str) -> str:
    """Actuator id for a FLEA run name, e.g. ``flea-sine11-nominal-20100903-095140``."""
    match = _FLEA_NAME.match(name)
    if match is None:
        return _slug(f"flea-{name}")
    date = match["date"].replace("_", "")
    clock = match["clock"].replace("_", "")
    return _slug(f"flea-{match['profile']}-{match['scenario']}-{date}-{clock}")


def is_flea_file(path: Path) -> bool:
    return path.name.endswith((".data.gz", ".data"))


def read_recording(path: Path, t_offset_s: float = 0.0) -> Recording:
    """Read a FLEA run or a generic CSV file (see the module docstring)."""
    if is_flea_file(path):
        from estimators.flea import read_flea_run

        run = read_flea_run(path)
        return Recording(
            path=path,
            name=run.name,
            t_s=run.t0_epoch_s + run.t_s + t_offset_s,
            channels={"current": run.current_a, "voltage": run.voltage_v},
            actuator_id=flea_actuator_id(run.name),
            description=f"FLEA {run.scenario}, motor {run.motor}, {len(run)} samples",
        )
    return _read_csv(path, t_offset_s)


def _read_csv(path: Path, t_offset_s: float) -> Recording:
    import pyarrow as pa
    import pyarrow.csv as pa_csv

    with open(path, "rb") as fh:
        header = fh.readline().decode("utf-8-sig").strip()
    names = [name.strip().strip('"') for name in header.split(",")]
    if "t" not in names:
        raise ValueError(f"{path}: a CSV recording needs a header row with a 't' column")
    table = pa_csv.read_csv(
        path,
        convert_options=pa_csv.ConvertOptions(
            column_types={name: pa.float64() for name in names},
            null_values=["", "NaN", "nan", "NA", "null"],
            strings_can_be_null=True,
        ),
    )
    columns = {
        name: table.column(name).to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        for name in table.column_names
    }
    t_s = columns.pop("t") + t_offset_s
    if not columns:
        raise ValueError(f"{path}: no channel columns besides 't'")
    name = path.name.removesuffix(".gz").removesuffix(".csv")
    return Recording(
        path=path,
        name=name,
        t_s=t_s,
        channels=columns,
        actuator_id=_slug(name),
        description=f"CSV, channels {', '.join(columns)}, {len(t_s)} samples",
    )


def expand_paths(paths: Sequence[str]) -> list[Path]:
    """Files named, and the ``*.data.gz`` / ``*.data`` / ``*.csv`` files of folders named."""
    files: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            found = [
                p
                for p in sorted(path.rglob("*"))
                if p.is_file()
                and (is_flea_file(p) or p.name.endswith(".csv"))
                and p.name != "index.csv"
            ]
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise FileNotFoundError(f"no such file or folder: {path}")
    return files


@dataclass
class ReplayResult:
    """Counts of a replay, and the last acknowledged sequence of each actuator."""

    batches_sent: int = 0
    samples_sent: int = 0
    replayed: int = 0
    errors: int = 0
    last_seq: dict[str, int] | None = None


def replay_recordings(
    client: FleetHealthClient,
    recordings: Sequence[Recording],
    *,
    tail: str,
    actuator: str | None = None,
    kind: str = ACTUATOR_KIND,
    fmt: str = "arrow",
    batch_samples: int = 1000,
    speed: float = 0.0,
    log: Any = print,
) -> ReplayResult:
    """Send recordings in order of their first time stamp; register aircraft and actuators first.

    ``speed`` paces sending on the wall clock (1 = real time, 2 = twice as fast); 0 sends as fast
    as the server takes batches. Gaps between files are not waited for.
    """
    if batch_samples < 1:
        raise ValueError("batch_samples must be at least 1")
    if speed < 0:
        raise ValueError("speed must be >= 0")
    ordered = sorted(recordings, key=lambda r: float(r.t_s[0]) if len(r) else float("inf"))
    result = ReplayResult(last_seq={})
    assert result.last_seq is not None
    client.create_aircraft(tail, description="replayed recordings")
    registered: set[str] = set()
    for rec in ordered:
        actuator_id = actuator or rec.actuator_id
        if actuator_id not in registered:
            client.create_actuator(tail, actuator_id, kind=kind, channels=list(rec.channels))
            registered.add(actuator_id)
        log(f"replay: {rec.name} -> {tail}/{actuator_id} ({rec.description})")
        if len(rec) == 0:
            continue
        wall_start = time.monotonic()
        t_first = float(rec.t_s[0])
        for start in range(0, len(rec), batch_samples):
            stop = min(start + batch_samples, len(rec))
            t_batch = rec.t_s[start:stop]
            if speed > 0:
                ahead_s = (float(t_batch[-1]) - t_first) / speed - (time.monotonic() - wall_start)
                if ahead_s > 0:
                    time.sleep(ahead_s)
            batch_id = f"{_slug(rec.name, 96)}-{start}"
            channels = {name: values[start:stop] for name, values in rec.channels.items()}
            try:
                ack = client.post_batch(tail, actuator_id, batch_id, channels, t_s=t_batch, fmt=fmt)
            except ApiError as exc:
                result.errors += 1
                log(f"replay: {rec.name} samples {start}-{stop - 1}: {exc}")
                if exc.status < 500:
                    # The rest of this file would fail the same way (stale, unknown channel...).
                    break
                continue
            result.batches_sent += 1
            result.samples_sent += stop - start
            result.last_seq[actuator_id] = int(ack["seq"])
    return result


def format_health(health: dict[str, Any]) -> str:
    """A few lines summarizing one actuator's health answer."""
    lines = [
        f"{health.get('tail')}/{health.get('actuator_id')}: status {health.get('status')}, "
        f"applied seq {health.get('last_applied_seq')}, t_last {health.get('t_last_s')}"
    ]
    for name, est in (health.get("estimators") or {}).items():
        window = est.get("window") or {}
        reasons = "; ".join(est.get("reasons") or []) or "-"
        lines.append(f"  {name}: {est.get('status')} ({reasons})")
        for key, value in (window.get("indicators") or {}).items():
            shown = f"{value:.6g}" if isinstance(value, float) else str(value)
            lines.append(f"    {key} = {shown}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``fleethealth replay``."""
    parser.description = (
        "Send recorded runs to a running server. FLEA run files (*.data.gz) send the driven "
        "motor's current and voltage; a CSV file needs a header row and a 't' column (seconds), "
        "its other columns being channels. Without --actuator each file becomes its own actuator, "
        "named from the file (e.g. flea-sine11-nominal-20100903-095140); with --actuator every "
        "file goes to that one actuator in order of first time stamp, as one increasing stream. "
        "Times are absolute (FLEA: start of run + offset). Batch ids come from the file name and "
        "sample offset, so a repeated replay sends nothing twice."
    )
    parser.add_argument("paths", nargs="+", help="run files, or folders to search for them")
    parser.add_argument(
        "--url",
        default=os.environ.get("FLEETHEALTH_URL", DEFAULT_URL),
        help=f"server address (env FLEETHEALTH_URL; default {DEFAULT_URL})",
    )
    parser.add_argument(
        "--api-key",
        default=os.environ.get("FLEETHEALTH_API_KEY"),
        help="API key (env FLEETHEALTH_API_KEY); registering needs admin scope",
    )
    parser.add_argument(
        "--tail", default=DEFAULT_TAIL, help=f"aircraft tail (default {DEFAULT_TAIL})"
    )
    parser.add_argument(
        "--actuator",
        default=None,
        help="send all files to this one actuator (default: one actuator per file)",
    )
    parser.add_argument("--kind", default=ACTUATOR_KIND, help=f"actuator kind ({ACTUATOR_KIND})")
    parser.add_argument("--format", choices=BATCH_FORMATS, default="arrow", dest="fmt")
    parser.add_argument(
        "--batch-samples", type=int, default=1000, help="samples per batch (default 1000)"
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=0.0,
        help="0 = as fast as possible (default), 1 = real time, 10 = ten times real time; "
        "gaps between files are skipped",
    )
    parser.add_argument(
        "--t-offset-s", type=float, default=0.0, help="seconds added to every time stamp"
    )
    parser.add_argument(
        "--wait",
        action="store_true",
        help="wait until the server has applied every batch and print each actuator's health",
    )
    parser.add_argument(
        "--wait-timeout-s",
        type=float,
        default=120.0,
        help="limit for --wait once the server's kernels are ready (default 120); the wait for "
        "the kernels themselves has no limit",
    )


def run(args: argparse.Namespace) -> int:
    """Entry point of ``fleethealth replay``; returns the process exit code."""
    if not args.api_key:
        print("replay: give --api-key or set FLEETHEALTH_API_KEY", file=sys.stderr)
        return 2
    try:
        files = expand_paths(args.paths)
        recordings = [read_recording(path, args.t_offset_s) for path in files]
    except (OSError, ValueError) as exc:
        print(f"replay: {exc}", file=sys.stderr)
        return 2
    if not recordings:
        print("replay: no run files found", file=sys.stderr)
        return 2
    started = time.monotonic()
    with FleetHealthClient(args.url, args.api_key) as client:
        try:
            result = replay_recordings(
                client,
                recordings,
                tail=args.tail,
                actuator=args.actuator,
                kind=args.kind,
                fmt=args.fmt,
                batch_samples=args.batch_samples,
                speed=args.speed,
            )
        except ApiError as exc:
            print(f"replay: {exc}", file=sys.stderr)
            return 1
        elapsed = time.monotonic() - started
        rate = result.samples_sent / elapsed if elapsed > 0 else 0.0
        print(
            f"replay: {result.batches_sent} batches, {result.samples_sent} samples in "
            f"{elapsed:.2f} s ({rate:,.0f} samples/s), {result.errors} errors"
        )
        if args.wait and result.last_seq:
            # A fresh server may still compile the kernels these streams need (minutes on a new
            # installation): wait for them however long it takes, then for the applies.
            kinds: set[str] = set()
            for actuator_id in result.last_seq:
                kinds.update(client.health(args.tail, actuator_id).get("estimators") or {})
            wait_for_server(client, kinds=kinds or None, prefix="replay: ")
            for actuator_id, seq in result.last_seq.items():
                try:
                    health = client.wait_applied(
                        args.tail, actuator_id, seq, timeout_s=args.wait_timeout_s
                    )
                except TimeoutError as exc:
                    print(f"replay: {exc}", file=sys.stderr)
                    return 1
                print(format_health(health))
    return 0 if result.errors == 0 else 1
