"""The shortcuts a small batch takes give what the general path gives: the JSON lists of a few
values turned into arrays without Arrow, and a small block written as the IPC stream writer
writes it."""

from __future__ import annotations

import warnings

import numpy as np
import pyarrow as pa
import pytest

from app import ingest
from app.codec import COMPRESS_MIN_ROWS, decode_columns, encode_columns
from app.errors import InvalidBatch
from app.ingest import ParsedBatch, TimeParams, parse_body
from app.telemetry.validation import check_batch, decoding_guard

LISTS = [
    [0.3],
    [1, 2.5, None],
    [None, None],
    [],
    [2**53, -(2**53), 0],
    [1e308, -1e-308, 0.0, -0.0],
    [1, 2, 3],
]


@pytest.mark.parametrize("values", LISTS)
def test_small_lists_become_the_arrays_arrow_makes(values: list[object], monkeypatch: pytest.MonkeyPatch) -> None:
    small = ingest._to_float_array(list(values), "c")
    monkeypatch.setattr(ingest, "SMALL_LIST_MAX", -1)  # every list through Arrow
    general = ingest._to_float_array(list(values), "c")
    assert small.dtype == general.dtype == np.float64
    np.testing.assert_array_equal(small, general)
    assert [np.signbit(x) for x in small] == [np.signbit(x) for x in general]


@pytest.mark.parametrize("values", [[2**53 + 1], [1.5, -(2**53) - 1], [True], ["1"], [1, [2]], [{"a": 1}]])
def test_values_the_shortcut_leaves_get_arrows_refusal(values: list[object], monkeypatch: pytest.MonkeyPatch) -> None:
    def refusal() -> str:
        with pytest.raises(InvalidBatch) as err, decoding_guard():
            ingest._to_float_array(list(values), "c")
        return err.value.detail

    small = refusal()
    monkeypatch.setattr(ingest, "SMALL_LIST_MAX", -1)
    assert small == refusal()


def _stream_writer_bytes(columns: dict[str, np.ndarray]) -> bytes:
    table = pa.table({k: pa.array(np.asarray(v, dtype=np.float64)) for k, v in columns.items()})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return bytes(sink.getvalue().to_pybytes())


@pytest.mark.parametrize("rows", [1, 2, 17, COMPRESS_MIN_ROWS - 1])
def test_a_small_block_is_the_stream_writers_bytes(rows: int) -> None:
    rng = np.random.default_rng(rows)
    columns = {"t": np.arange(rows, dtype=np.float64), "current": rng.normal(size=rows),
               "voltage": np.where(rng.random(rows) < 0.3, np.nan, rng.normal(size=rows))}
    data = encode_columns(columns)
    assert data == _stream_writer_bytes(columns)
    decoded = decode_columns(data)
    for name, col in columns.items():
        np.testing.assert_array_equal(decoded[name], col)
    # Another set of names: its own schema; many columns (a sample's outputs).
    renamed = {"t": columns["t"], "x": columns["current"]}
    assert encode_columns(renamed) == _stream_writer_bytes(renamed)
    outputs = {f"out{i}": rng.normal(size=rows) for i in range(36)}
    assert encode_columns(outputs) == _stream_writer_bytes(outputs)


def test_blocks_the_shortcut_leaves_are_encoded_as_before() -> None:
    empty = {"t": np.array([], dtype=np.float64)}
    assert encode_columns(empty) == _stream_writer_bytes(empty)
    strided = {"t": np.arange(20.0)[::2], "n": np.arange(10)}
    assert encode_columns(strided) == _stream_writer_bytes(strided)
    with pytest.raises(pa.ArrowInvalid):
        encode_columns({"a": np.zeros(3), "b": np.zeros(2)})


def test_missing_samples_raise_no_floating_point_warning() -> None:
    batch = ParsedBatch("b", np.array([1.0, 2.0]), {"current": np.array([np.nan, 0.5]), "voltage": np.array([np.nan] * 2)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(all="raise"):
            check_batch(batch)


def test_a_one_sample_body_parses_as_before() -> None:
    body = b'{"batch_id":"m1","t":[1700000000.01],"channels":{"current":[0.3],"voltage":[null]}}'
    batch = parse_body(body, "application/json", TimeParams(None, None, None), ["current", "voltage"], 10)
    assert batch.batch_id == "m1" and batch.t_s.tolist() == [1700000000.01]
    assert batch.channels["current"].tolist() == [0.3] and np.isnan(batch.channels["voltage"][0])
