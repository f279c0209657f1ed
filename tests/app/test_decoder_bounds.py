"""Decoders are bounded before they allocate: a small compressed body that would expand to tens
of millions of rows is refused with the sample-limit error, and memory does not grow with it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.errors import InvalidBatch
from app.ingest import ARROW_TYPES, CSV_TYPES, JSON_TYPES, TimeParams, parse_body, parse_frame
from app.main import create_app
from tests.app.conftest import Api, arrow_bytes, make_settings

TEL = "/v1/aircraft/N1/actuators/ema1/telemetry"
CHANNELS = ["current", "voltage"]
BOMB_ROWS = 50_000_000
DEFAULT_MAX_SAMPLES = 5_000_000
# Peak memory a refused bomb may add to the process. Decoding the bomb whole takes the int8
# columns (3 x 50 MB) and their float64 casts (3 x 400 MB): well above 1 GB.
MAX_RSS_GROWTH_MB = 200.0


def _ipc(table: pa.Table, compression: str | None = "zstd") -> bytes:
    sink = pa.BufferOutputStream()
    options = pa.ipc.IpcWriteOptions(compression=compression)
    with pa.ipc.new_stream(sink, table.schema, options=options) as w:
        w.write_table(table)  # one record batch
    return sink.getvalue().to_pybytes()  # type: ignore[no-any-return]


def _bomb(rows: int = BOMB_ROWS, metadata: dict[str, str] | None = None) -> bytes:
    """One zstd record batch of ``rows`` zeros per column: tens of kilobytes on the wire."""
    zeros = pa.py_buffer(bytes(rows))
    col = pa.Array.from_buffers(pa.int8(), rows, [None, zeros])
    table = pa.table({"t": col, "current": col, "voltage": col})
    if metadata:
        table = table.replace_schema_metadata(metadata)
    return _ipc(table)


@pytest.fixture(scope="module")
def bomb_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bomb") / "bomb.arrows"
    path.write_bytes(_bomb(metadata={"client_seq": "1"}))
    return path


_PROBE = textwrap.dedent(
    """
    import resource, sys
    from app.errors import InvalidBatch
    from app.ingest import ARROW_TYPES, TimeParams, parse_body, parse_frame

    body = open(sys.argv[1], "rb").read()
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        if sys.argv[2] == "frame":
            parse_frame(body, ["current", "voltage"], int(sys.argv[3]))
        else:
            parse_body(body, ARROW_TYPES[0], TimeParams("b1", None, None), ["current", "voltage"],
                       int(sys.argv[3]))
        print("accepted")
    except InvalidBatch as exc:
        print("refused:", exc.detail)
    after_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print((after_kb - before_kb) / 1024.0)
    """
)


@pytest.mark.parametrize("path", ["body", "frame"])
def test_an_arrow_bomb_is_refused_without_being_decompressed(bomb_path: Path, path: str) -> None:
    # Peak RSS is measured in a fresh process, so nothing earlier in the test run masks it.
    assert bomb_path.stat().st_size < 256 * 1024  # small on the wire, 50 M rows declared
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, str(bomb_path), path, str(DEFAULT_MAX_SAMPLES)],
        capture_output=True, text=True, env=env, timeout=300, check=True,
    ).stdout.splitlines()
    assert out[0].startswith("refused:") and f"the limit is {DEFAULT_MAX_SAMPLES}" in out[0], out
    growth_mb = float(out[1])
    assert growth_mb < MAX_RSS_GROWTH_MB, f"peak RSS grew by {growth_mb:.0f} MB while refusing the bomb"


def test_an_arrow_bomb_gets_the_sample_limit_error_over_http_and_websocket(api: Api) -> None:
    api.setup_actuator()
    r = api.post(TEL + "?batch_id=b1", content=_bomb(rows=20_000_000),
                 headers={"content-type": ARROW_TYPES[0]})
    assert r.status_code == 400, r.text
    assert r.json()["error"] == "InvalidBatch" and "the limit is 5000000" in r.json()["detail"]
    with api.c.websocket_connect("/v1/aircraft/N1/actuators/ema1/stream", headers=api.h) as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_bytes(_bomb(rows=20_000_000, metadata={"client_seq": "1"}))
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "InvalidBatch" and "the limit is" in err["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1007
    assert api.health()["last_logged_seq"] == 0


def _table(n: int) -> pa.Table:
    return pa.table({"t": np.arange(n) * 1e-3, "current": np.zeros(n), "voltage": np.ones(n)})


@pytest.mark.parametrize("compression", ["zstd", "lz4", None])
def test_arrow_batches_within_the_limits_decode_as_before(compression: str | None) -> None:
    table = _table(1000)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema, options=pa.ipc.IpcWriteOptions(compression=compression)) as w:
        w.write_table(table, max_chunksize=300)  # four record batches
    got = parse_body(sink.getvalue().to_pybytes(), ARROW_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000)
    assert got.n_samples == 1000
    np.testing.assert_array_equal(got.t_s, np.arange(1000) * 1e-3)
    np.testing.assert_array_equal(got.channels["voltage"], np.ones(1000))


def test_the_row_count_is_summed_over_record_batches() -> None:
    table = _table(1000)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table, max_chunksize=300)
    with pytest.raises(InvalidBatch, match="at least 900 samples; the limit is 800"):
        parse_body(sink.getvalue().to_pybytes(), ARROW_TYPES[0], TimeParams("b1", None, None), CHANNELS, 800)


def test_wide_values_are_refused_by_their_decompressed_size() -> None:
    # Few rows, but each value of this (not numeric) column decompresses to 1 MB: the byte
    # limit stops it before it is decompressed, whatever its type.
    n = 4
    wide = pa.array([bytes(1_000_000)] * n, type=pa.binary())
    table = pa.table({"t": np.arange(n) * 1.0, "current": wide, "voltage": np.zeros(n)})
    body = _ipc(table)
    assert len(body) < 100_000
    with pytest.raises(InvalidBatch, match="decodes to more than"):
        parse_body(body, ARROW_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000)


def test_more_columns_than_channels_are_refused_before_decoding() -> None:
    n = 10
    table = pa.table({"t": np.arange(n) * 1.0, **{f"c{i}": np.zeros(n) for i in range(50)}})
    with pytest.raises(InvalidBatch, match="51 columns"):
        parse_body(_ipc(table), ARROW_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000)
    csv = ("t," + ",".join(f"c{i}" for i in range(50)) + "\n1" + ",0" * 50 + "\n").encode()
    with pytest.raises(InvalidBatch, match="51 columns"):
        parse_body(csv, CSV_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000)


def test_a_frame_bomb_is_refused_by_parse_frame() -> None:
    with pytest.raises(InvalidBatch, match="the limit is 1000"):
        parse_frame(_bomb(rows=1_000_000, metadata={"client_seq": "1"}), CHANNELS, 1000)


def test_a_long_csv_is_refused_by_its_row_count() -> None:
    rows = b"".join(b"%d,0,1\n" % i for i in range(5000))
    body = b"t,current,voltage\n" + rows
    with pytest.raises(InvalidBatch, match="the limit is 1000"):
        parse_body(body, CSV_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000)
    # Blank lines make the newline count loose: the rows are then counted exactly.
    sparse = b"t,current,voltage\n" + b"\n" * 5000 + b"".join(b"%d,0,1\n" % i for i in range(500))
    assert parse_body(sparse, CSV_TYPES[0], TimeParams("b1", None, None), CHANNELS, 1000).n_samples == 500


def test_a_csv_column_whose_type_changes_after_the_first_block_still_reads() -> None:
    # Type inference over the whole body, as before the bound: ints for 300k rows, then a float.
    n = 300_000
    body = b"t,current,voltage\n" + b"".join(b"%d,%d,0\n" % (i, i) for i in range(n)) + b"300001,1.5,0\n"
    got = parse_body(body, CSV_TYPES[0], TimeParams("b1", None, None), CHANNELS, n + 1)
    assert got.n_samples == n + 1 and got.channels["current"][-1] == 1.5


def test_a_json_body_with_too_many_values_is_refused_before_parsing() -> None:
    body = b'{"batch_id": "b1", "t0": 0, "sample_rate_hz": 1, "channels": {"current": [' + b"0," * 5000 + \
        b'0], "voltage": [0]}}'
    with pytest.raises(InvalidBatch, match="the limit is 1000 samples"):
        parse_body(body, JSON_TYPES[0], TimeParams(None, None, None), CHANNELS, 1000)
    with pytest.raises(InvalidBatch, match="the limit is 1000 samples"):
        parse_frame(body.decode().replace('"batch_id": "b1"', '"type": "samples", "client_seq": 1'), CHANNELS, 1000)


def test_the_decoded_bytes_setting_bounds_what_the_service_accepts(db_url: str) -> None:
    # The service's own setting, not a process-wide default, caps the decoded size: 1,000
    # samples of three float64 columns decode to about 27 kB, above a 10 kB cap.
    settings = make_settings(db_url, max_batch_decoded_bytes=10_000)
    with TestClient(create_app(settings)) as client:
        api = Api(client)
        api.setup_actuator()
        body = arrow_bytes({"t": np.arange(1000) * 1e-3, "current": np.zeros(1000), "voltage": np.ones(1000)})
        r = api.post(TEL + "?batch_id=b1", content=body, headers={"content-type": ARROW_TYPES[0]})
        assert r.status_code == 400 and "decodes to more than" in r.json()["detail"], r.text
        small = arrow_bytes({"t": np.arange(100) * 1e-3, "current": np.zeros(100), "voltage": np.ones(100)})
        r = api.post(TEL + "?batch_id=b2", content=small, headers={"content-type": ARROW_TYPES[0]})
        assert r.status_code == 202, r.text
