"""Arrow IPC bodies, with pyarrow as an optional dependency.

pyarrow is imported on first use only, so that the JSON encoding, the REST clients and the JSON
WebSocket frames work on an install without it (``pip install fleethealth-client``); the Arrow
and CSV encodings and binary frames need ``pip install "fleethealth-client[arrow]"``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import ModuleType

from fleethealth_client.columns import FloatArray

__all__ = ["PYARROW_MISSING", "ipc_stream", "require_pyarrow"]

PYARROW_MISSING = (
    "the {what} needs pyarrow, which is not installed: "
    'pip install "fleethealth-client[arrow]" (or use the JSON encoding)'
)


def require_pyarrow(what: str = "Arrow encoding") -> ModuleType:
    """The ``pyarrow`` module (with ``pyarrow.ipc`` loaded).

    Args:
        what: what needs it, for the error message.

    Raises:
        ImportError: pyarrow is not installed; the message says how to install it.
    """
    try:
        import pyarrow
        import pyarrow.ipc
    except ImportError as exc:
        raise ImportError(PYARROW_MISSING.format(what=what)) from exc
    module: ModuleType = pyarrow
    return module


def ipc_stream(
    names: Sequence[str],
    arrays: Sequence[FloatArray],
    metadata: Mapping[str, str] | None = None,
    *,
    what: str = "Arrow encoding",
) -> bytes:
    """One record batch of float64 columns as an Arrow IPC stream (NaN kept as a float NaN).

    Args:
        names: column names.
        arrays: one float64 array per name, of equal lengths.
        metadata: optional schema metadata (WebSocket frames carry ``client_seq`` there).
        what: what asks for it, for the error message when pyarrow is missing.
    """
    pa = require_pyarrow(what)
    record_batch = pa.record_batch(
        [pa.array(arr, type=pa.float64()) for arr in arrays], names=list(names)
    )
    if metadata:
        record_batch = record_batch.replace_schema_metadata(dict(metadata))
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, record_batch.schema) as writer:
        writer.write_batch(record_batch)
    content: bytes = sink.getvalue().to_pybytes()
    return content
