"""Peak memory of a streamed telemetry export against the size of the series it exports.

One process fills a SQLite log with ``--batches`` batches of ``--samples`` samples (t + 2
channels); then a fresh process per case exports the whole stream through the service's read-back path
(``app.telemetry.readback.export_blocks`` -> ``app.series.export``), consuming the chunks as an
HTTP body would, and notes the peak RSS above what it was before the export. ``whole`` reads the
same blocks into one table first (what a non-streamed export would hold), for comparison.

    .venv/bin/python bench/bench_export_memory.py [--batches 100 --samples 20000]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child(case: str, batches: int, samples: int, db_dir: str) -> None:
    import numpy as np

    from app.codec import encode_columns
    from app.db import Database
    from app.migrate import upgrade
    from app.models import Actuator, Aircraft, Operator, Stream, TelemetryBatch

    url = f"sqlite:///{db_dir}/bench.db"
    if case != "fill":
        export_case(case, url)
        return
    upgrade(url)
    db = Database(url)
    rng = np.random.default_rng(0)
    with db.write() as s:
        op = Operator(name="bench")
        s.add(op)
        s.flush()
        ac = Aircraft(operator_id=op.id, tail="B1")
        s.add(ac)
        s.flush()
        act = Actuator(aircraft_id=ac.id, actuator_id="a", kind="ema_voltage", channels=["current", "voltage"])
        s.add(act)
        s.flush()
        s.add(Stream(actuator_pk=act.id))
        for k in range(batches):
            t = (k * samples + np.arange(samples)) * 1e-3
            s.add(TelemetryBatch(
                actuator_pk=act.id, seq=k + 1, batch_id=f"b{k}", content_hash="x", n_samples=samples,
                t_first_s=float(t[0]), t_last_s=float(t[-1]),
                payload=encode_columns({"t": t, "current": rng.normal(size=samples), "voltage": rng.normal(size=samples)}),
            ))
            if k % 10 == 9:
                s.flush()
                s.expunge_all()
                act = s.get(Actuator, 1)  # type: ignore[assignment]
    db.dispose()


def export_case(case: str, url: str) -> None:
    import pyarrow as pa

    from app import series
    from app.db import Database
    from app.models import Actuator
    from app.telemetry import readback

    db = Database(url)
    pk = 1
    base = _rss_mb()
    out_bytes = 0
    with db.read() as s:
        act = s.get(Actuator, pk)
        assert act is not None
        schema, blocks = readback.export_blocks(s, act, None, None)
        if case == "whole":
            table = pa.Table.from_batches(
                [pa.record_batch([pa.array(b[f.name]) for f in schema], schema=schema) for b in blocks]
            )
            out_bytes = table.nbytes
        else:
            for chunk in series.export(blocks, schema, case):  # type: ignore[arg-type]
                out_bytes += len(chunk)
        n = sum(b.n_samples for b in readback.repository.logged_blocks(s, pk, None, None))
    print(json.dumps({"case": case, "peak_mb": _rss_mb() - base, "out_mb": out_bytes / 1e6,
                      "series_mb": n * 3 * 8 / 1e6}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", type=int, default=100)
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--child", default=None)
    ap.add_argument("--db-dir", default=None)
    a = ap.parse_args()
    if a.child:
        child(a.child, a.batches, a.samples, a.db_dir)
        return
    print(f"{a.batches} batches x {a.samples} samples (t + 2 channels, float64)")
    print(f"{'case':>8} {'series MB':>10} {'file MB':>9} {'extra peak RSS MB':>18} {'peak / series':>14}")
    with tempfile.TemporaryDirectory() as d:
        def run(case: str) -> str:
            return subprocess.run(
                [sys.executable, __file__, "--child", case, "--batches", str(a.batches), "--samples", str(a.samples),
                 "--db-dir", d], capture_output=True, text=True, check=True,
            ).stdout.strip()

        run("fill")
        results = [json.loads(run(case).splitlines()[-1]) for case in ("arrow", "parquet", "csv", "whole")]
    for r in results:
        case = r["case"]
        print(f"{case:>8} {r['series_mb']:10.1f} {r['out_mb']:9.1f} {r['peak_mb']:18.1f} {r['peak_mb'] / r['series_mb']:14.2f}")


if __name__ == "__main__":
    main()
