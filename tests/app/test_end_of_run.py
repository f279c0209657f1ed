"""The end-of-run marker: accepted in JSON, CSV/Arrow (query) and frames, stored with the
batch, part of its idempotent identity, and handed to the estimators."""

from __future__ import annotations

from typing import Any

import orjson
import pyarrow as pa
import pytest
from sqlalchemy import select

from app.db import Database
from app.ingest import parse_frame
from app.models import TelemetryBatch
from estimators import fakf
from tests.app.conftest import Api, arrow_bytes
from tests.conftest import make_series

URL = "/v1/aircraft/N1/actuators/ema1/telemetry"


def _json(batch_id: str, t: Any, i: Any, v: Any, **extra: Any) -> bytes:
    doc = {"batch_id": batch_id, "t": t, "channels": {"current": i, "voltage": v}, **extra}
    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)


def test_marker_is_stored_passed_to_the_estimators_and_part_of_the_identity(
    api: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    api.setup_actuator()
    # The start-up kernel warm-up steps the estimators in a background thread: record only
    # after it has finished, so it neither lands in the record nor meets the recorder.
    assert api.app.state.kernels_warm.wait(300)
    seen: list[tuple[float, bool]] = []
    real_step = fakf.step

    def recording_step(cfg, state, batch):  # type: ignore[no-untyped-def]
        seen.append((float(batch.t_s[0]) if len(batch) else float("nan"), batch.end_of_run))
        return real_step(cfg, state, batch)

    monkeypatch.setattr(fakf, "step", recording_step)
    s = make_series(900, seed=31)
    h = {"content-type": "application/json"}
    r = api.post(f"{URL}?wait=30", content=_json("a", s.t_s[:300], s.current[:300], s.voltage[:300]), headers=h)
    assert r.status_code == 202 and r.json()["end_of_run"] is False
    body = _json("b", s.t_s[300:600], s.current[300:600], s.voltage[300:600], end_of_run=True)
    r = api.post(f"{URL}?wait=30", content=body, headers=h)
    assert r.status_code == 202 and r.json()["end_of_run"] is True, r.text
    # The same id and samples without the marker is another batch: a conflict, not a retry.
    other = _json("b", s.t_s[300:600], s.current[300:600], s.voltage[300:600])
    r = api.post(URL, content=other, headers=h)
    assert r.status_code == 409 and r.json()["error"] == "IdempotencyConflict"
    r = api.post(URL, content=body, headers=h)
    assert r.status_code == 202 and r.headers["idempotent-replayed"] == "true"
    # Arrow (and CSV) bodies carry it as a query parameter.
    arrow = arrow_bytes({"t": s.t_s[600:], "current": s.current[600:], "voltage": s.voltage[600:]})
    r = api.post(f"{URL}?batch_id=c&end_of_run=true&wait=30", content=arrow,
                 headers={"content-type": "application/vnd.apache.arrow.stream"})
    assert r.status_code == 202 and r.json()["end_of_run"] is True
    r = api.post(URL, content=_json("d", [2.0], [1.0], [1.0], end_of_run="yes"), headers=h)
    assert r.status_code == 400 and "end_of_run" in r.json()["detail"]

    assert seen == [(s.t_s[0], False), (s.t_s[300], True), (s.t_s[600], True)]
    db = Database(db_url)
    with db.read() as session:
        stored = [(b.batch_id, b.end_of_run) for b in session.scalars(select(TelemetryBatch).order_by(TelemetryBatch.seq))]
    db.dispose()
    assert stored == [("a", False), ("b", True), ("c", True)]


def test_frames_carry_the_marker_in_both_encodings() -> None:
    chans = ["current", "voltage"]
    doc = {"type": "samples", "client_seq": 3, "t": [0.0, 0.1], "channels": {"current": [1, 2], "voltage": [3, 4]}}
    _, plain = parse_frame(orjson.dumps(doc).decode(), chans, 100)
    _, marked = parse_frame(orjson.dumps({**doc, "end_of_run": True}).decode(), chans, 100)
    assert (plain.end_of_run, marked.end_of_run) == (False, True)
    assert plain.content_hash() != marked.content_hash()
    rb = pa.record_batch([pa.array([0.0, 0.1]), pa.array([1.0, 2.0]), pa.array([3.0, 4.0])], names=["t", *chans])
    for meta, expected in (({"client_seq": "3"}, False), ({"client_seq": "3", "end_of_run": "true"}, True)):
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, rb.schema.with_metadata(meta)) as w:
            w.write_batch(rb)
        _, batch = parse_frame(sink.getvalue().to_pybytes(), chans, 100)
        assert batch.end_of_run is expected
    assert marked.content_hash() == batch.content_hash()
