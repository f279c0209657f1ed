"""Python client of the fleethealth API: REST (sync and asyncio) and WebSocket streaming.

The names most code needs are importable from here; each lives in one module:

* :mod:`fleethealth_client.client` -- :class:`FleetHealthClient`, :class:`AsyncFleetHealthClient`;
* :mod:`fleethealth_client.streaming` -- :class:`FrameStreamer` (WebSocket frames with resume);
* :mod:`fleethealth_client.encoding` -- telemetry encodings (JSON, CSV, Arrow);
* :mod:`fleethealth_client.errors` -- :class:`ApiError`, :class:`StreamRefused`;
* :mod:`fleethealth_client.retry` -- :class:`RetryPolicy`;
* :mod:`fleethealth_client.columns`, :mod:`fleethealth_client.arrow`,
  :mod:`fleethealth_client.paths` -- pieces shared by the REST and WebSocket sides.

pyarrow is optional (``pip install "fleethealth-client[arrow]"``): without it the JSON encoding
and JSON frames work, and asking for Arrow or CSV raises an ImportError saying what to install.
"""

from __future__ import annotations

from fleethealth_client.client import AsyncFleetHealthClient, FleetHealthClient
from fleethealth_client.encoding import (
    ARROW_STREAM_MEDIA_TYPE,
    BATCH_FORMATS,
    EncodedBatch,
    encode_batch,
    encode_batch_arrow,
    encode_batch_csv,
    encode_batch_json,
)
from fleethealth_client.errors import ApiError, StreamRefused
from fleethealth_client.retry import RetryPolicy
from fleethealth_client.streaming import FrameStreamer, StreamStats, encode_frame, frames_of

__version__ = "0.1.0"

__all__ = [
    "ARROW_STREAM_MEDIA_TYPE",
    "BATCH_FORMATS",
    "ApiError",
    "AsyncFleetHealthClient",
    "EncodedBatch",
    "FleetHealthClient",
    "FrameStreamer",
    "RetryPolicy",
    "StreamRefused",
    "StreamStats",
    "encode_batch",
    "encode_batch_arrow",
    "encode_batch_csv",
    "encode_batch_json",
    "encode_frame",
    "frames_of",
]
