"""Peak memory of taking in one large batch, per format, against the batch's own size.

Each format runs in a fresh process: build the request body, note the peak RSS, then parse and
validate it and encode it for the telemetry log exactly as the API does, and note the peak again.
Prints the extra peak memory as a multiple of the float64 size of the samples (t + 2 channels).

    .venv/bin/python bench/bench_batch_memory.py [--samples 1000000]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys


def child(fmt: str, n: int) -> None:
    import io

    import numpy as np
    import orjson
    import pyarrow as pa

    from app.codec import encode_columns
    from app.ingest import TimeParams, parse_body

    rng = np.random.default_rng(0)
    t = np.arange(n) * 1e-3
    cur, volt = rng.normal(size=n), rng.normal(size=n)
    if fmt == "json":
        body = orjson.dumps(
            {
                "batch_id": "m",
                "t": t.tolist(),
                "channels": {"current": cur.tolist(), "voltage": volt.tolist()},
            }
        )
        mt = "application/json"
    elif fmt == "csv":
        buf = io.StringIO()
        np.savetxt(
            buf,
            np.column_stack([t, cur, volt]),
            delimiter=",",
            header="t,current,voltage",
            comments="",
            fmt="%.17g",
        )
        body = buf.getvalue().encode()
        mt = "text/csv"
    else:
        table = pa.table({"t": t, "current": cur, "voltage": volt})
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as w:
            w.write_table(table)
        body = sink.getvalue().to_pybytes()
        mt = "application/vnd.apache.arrow.stream"
    del t, cur, volt
    import gc

    gc.collect()
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    parsed = parse_body(body, mt, TimeParams("m", None, None), ["current", "voltage"], 10_000_000)
    payload = encode_columns({"t": parsed.t_s, **parsed.channels})
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(
        json.dumps(
            {
                "fmt": fmt,
                "body": len(body),
                "samples_bytes": 24 * n,
                "extra_peak": peak - base,
                "payload": len(payload),
            }
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--child", choices=["json", "csv", "arrow"])
    a = ap.parse_args()
    if a.child:
        child(a.child, a.samples)
        return
    print(
        f"one batch of {a.samples:,} samples (t + 2 channels, float64 = {24 * a.samples / 1e6:.0f} MB)"
    )
    print(
        f"{'format':<7}{'body MB':>9}{'extra peak MB':>15}{'x samples':>11}{'x body':>8}{'log MB':>8}"
    )
    for fmt in ("arrow", "csv", "json"):
        out = subprocess.run(
            [sys.executable, __file__, "--child", fmt, "--samples", str(a.samples)],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout)
        print(
            f"{fmt:<7}{r['body'] / 1e6:>9.1f}{r['extra_peak'] / 1e6:>15.1f}"
            f"{r['extra_peak'] / r['samples_bytes']:>11.2f}{r['extra_peak'] / r['body']:>8.2f}{r['payload'] / 1e6:>8.1f}"
        )


if __name__ == "__main__":
    main()
