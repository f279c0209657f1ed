"""Per-sample output retention keeps the last seconds of each stream's outputs, and only those."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from app.models import SampleOutputRow
from app.processing import repository
from tests.app.conftest import Api
from tests.conftest import make_series


def test_old_sample_outputs_dropped_per_stream(api: Api) -> None:
    s = make_series(3000, seed=5)  # 3 s at 1 kHz
    for act in ("ema1", "ema2"):
        api.setup_actuator("N1", act)
    for k, (a, b) in enumerate([(0, 1000), (1000, 2000), (2000, 3000)]):
        r = api.send_arrow("N1", "ema1", f"b{k}", s.t_s[a:b], {"current": s.current[a:b], "voltage": s.voltage[a:b]})
        assert r.status_code == 202, r.text
    # ema2 stops after its first second: its outputs are recent for its own stream.
    r = api.send_arrow("N1", "ema2", "b0", s.t_s[:1000], {"current": s.current[:1000], "voltage": s.voltage[:1000]})
    assert r.status_code == 202, r.text
    assert api.health("N1", "ema1")["last_applied_seq"] == 3
    assert api.health("N1", "ema2")["last_applied_seq"] == 1

    db = api.app.state.db
    with db.write() as session:
        dropped = repository.drop_old_sample_outputs(session, keep_s=1.5)
    with db.read() as session:
        kept = sorted(session.execute(select(SampleOutputRow.actuator_pk, SampleOutputRow.seq)).all())
    # ema1's last sample is at 2.999 s: its first batch (ends 0.999 s) is older than 1.5 s;
    # ema2's only batch ends at its own last sample and stays.
    assert dropped == 1
    assert sorted(seq for _, seq in kept) == [1, 2, 3]
    assert api.outputs("N1", "ema1")["t_s"][0] == s.t_s[1000]
    assert api.outputs("N1", "ema2")["t_s"][0] == s.t_s[0]


def test_demo_sets_retention_unless_told_otherwise(monkeypatch: pytest.MonkeyPatch) -> None:
    from app.cli import _demo_settings
    from app.config import Settings

    monkeypatch.delenv("FLEETHEALTH_LOG_RETENTION_S", raising=False)
    monkeypatch.delenv("FLEETHEALTH_SAMPLE_OUTPUT_RETENTION_S", raising=False)
    demo = _demo_settings(Settings())
    assert demo.log_retention_s == 600.0 and demo.sample_output_retention_s == 900.0
    monkeypatch.setenv("FLEETHEALTH_SAMPLE_OUTPUT_RETENTION_S", "7200")
    demo = _demo_settings(Settings())
    assert demo.sample_output_retention_s == 7200.0 and demo.log_retention_s == 600.0


def test_log_retention_drops_only_applied_payloads(api: Api) -> None:
    """A batch is applied when its seq is at or before its stream's applied mark (the log keeps
    no per-batch stamp): retention drops the payloads of those received before the cutoff, and
    keeps a batch not applied yet, however old."""
    from app.models import Stream, TelemetryBatch

    s = make_series(3000, seed=6)
    api.setup_actuator("N1", "ema1")
    for k, (a, b) in enumerate([(0, 1000), (1000, 2000), (2000, 3000)]):
        r = api.send_arrow("N1", "ema1", f"b{k}", s.t_s[a:b], {"current": s.current[a:b], "voltage": s.voltage[a:b]})
        assert r.status_code == 202, r.text
    assert api.health("N1", "ema1")["last_applied_seq"] == 3
    db = api.app.state.db
    with db.write() as session:
        # As if batch 3 were still pending: the stream's mark one batch back.
        st = session.scalar(select(Stream))
        assert st is not None
        st.last_applied_seq = 2
    with db.write() as session:
        assert repository.drop_applied_payloads(session, older_than_s=3600.0) == 0  # all recent
    with db.write() as session:
        dropped = repository.drop_applied_payloads(session, older_than_s=1e-9)
    with db.read() as session:
        kept = dict(session.execute(select(TelemetryBatch.seq, TelemetryBatch.payload.is_not(None))).all())
    assert dropped == 2
    assert kept == {1: False, 2: False, 3: True}
