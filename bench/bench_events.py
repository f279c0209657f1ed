"""Cost of the fleet event log and alarms inside the apply transaction.

On a migrated SQLite file (or PostgreSQL with ``--pg URL``), N actuators each get one logged
batch of constant current (the FAKF cannot identify a model: the status turns ``unknown``, so
the apply logs a ``status_changed`` event and raises an alarm) and one ordinary batch after it
(no fleet event). Each batch is applied with ``processing.service.apply_pending`` in its own
transaction, timed from the start of the transaction to its commit, with the hook as it is and
with the hook replaced by a no-op, side by side. Figures are printed; nothing is asserted.

Usage::

    .venv/bin/python bench/bench_events.py [--streams 40] [--pg postgresql+psycopg://...]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, text

from app.auth.service import get_or_create_operator
from app.config import Settings
from app.db import Database
from app.events import service as events
from app.fleet import service as fleet
from app.ingest import TimeParams
from app.kernels import warm_kind
from app.migrate import upgrade
from app.processing import service as processing
from app.telemetry import service as telemetry
from app.telemetry.body import RequestBody
from app.telemetry.validation import BatchLimits
from app.telemetry.writer import LogWriter

FAKF = {"fakf": {"identification_samples": 200, "health_window_samples": 250}}


def _json(batch_id: str, t: np.ndarray, cur: np.ndarray, volt: np.ndarray) -> bytes:
    import orjson

    return orjson.dumps({"batch_id": batch_id, "t": t.tolist(), "channels": {"current": cur.tolist(), "voltage": volt.tolist()}})


def run(url: str, streams: int, hook: bool) -> tuple[list[float], list[float]]:
    db = Database(url)
    settings = Settings(database_url=url)
    limits = BatchLimits.from_settings(settings)
    pks = []
    tail = f"B{uuid.uuid4().hex[:6]}"
    with db.write() as s:
        op_id = get_or_create_operator(s, "bench").id
        ac = fleet.create_aircraft(s, op_id, tail, None)
        for k in range(streams):
            act, _ = fleet.create_actuator(s, ac, f"a{k}", "ema_voltage", None, FAKF)
            pks.append((act.id, act.actuator_id))
    n = 800
    t = np.arange(n) * 0.001
    writer = LogWriter(db)
    writer.start()
    lookup = telemetry.ActuatorLookup(db, 0.0, 1)

    async def log(act_id: str, data: bytes) -> None:
        body = RequestBody(bytearray(data), None, len(data))
        await telemetry.ingest_body(writer, lookup, op_id, tail, act_id, body, "application/json",
                                    TimeParams(None, None, None), settings.max_batch_samples, limits)

    try:
        for _, act_id in pks:
            for i in range(2):
                asyncio.run(log(act_id, _json(f"b{i}", t + i, np.ones(n), np.ones(n))))
    finally:
        writer.stop()
    original = events.record_apply
    if not hook:
        events.record_apply = lambda session, result: []
    with_events: list[float] = []
    without: list[float] = []
    try:
        for pk, _ in pks:
            for out in (with_events, without):
                t0 = time.perf_counter()
                with db.write() as s:
                    res = processing.apply_pending(s, pk, max_samples=n, max_batches=1, store_outputs=True, is_sqlite=db.is_sqlite)
                out.append((time.perf_counter() - t0) * 1e3)
                assert res is not None and res.batches == 1
                # Which batch makes events is part of the set-up: check it, not the timing.
                changed = res.status_before != res.status_after
                assert changed == (out is with_events), (res.status_before, res.status_after)
    finally:
        events.record_apply = original
        db.dispose()
    return with_events, without


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--streams", type=int, default=40)
    ap.add_argument("--pg", default=None)
    args = ap.parse_args()
    warm_kind("fakf")
    if args.pg:
        schema = "b_" + uuid.uuid4().hex[:10]
        admin = create_engine(args.pg)
        with admin.begin() as c:
            c.execute(text(f'CREATE SCHEMA "{schema}"'))
        url = f"{args.pg}?options=-csearch_path%3D{schema}"
    else:
        url = f"sqlite:///{Path(tempfile.mkdtemp()) / 'bench.db'}"
    upgrade(url)
    rows: dict[bool, tuple[list[float], list[float]]] = {}
    for hook in (False, True, False, True):  # interleaved, so drift hits both alike
        ev, plain = run(url, args.streams, hook)
        rows.setdefault(hook, ([], []))
        rows[hook][0].extend(ev)
        rows[hook][1].extend(plain)
    print(f"apply transaction, median ms over {2 * args.streams} applies each ({'PostgreSQL' if args.pg else 'SQLite'})")
    print(f"{'':34} {'hook off':>10} {'hook on':>10}")
    for i, name in enumerate(("batch with a status change", "batch without fleet events")):
        off = statistics.median(rows[False][i])
        on = statistics.median(rows[True][i])
        print(f"{name:34} {off:10.2f} {on:10.2f}")
    if args.pg:
        with admin.begin() as c:
            c.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))


if __name__ == "__main__":
    main()
