"""Checks and shapes shared by the REST batch encoders and the WebSocket frames.

A batch is one or more named float64 channels of equal length, with times given either per sample
(``t_s``) or as a start ``t0`` and a ``sample_rate_hz``. NaN is a missing sample; infinite values
are refused before sending (the server answers 400 for them, and JSON has no way to write them).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "TIME_COLUMN",
    "FloatArray",
    "as_float_columns",
    "query_params",
    "table_columns",
    "time_params",
]

FloatArray = NDArray[np.float64]
#: Name of the time column in table bodies (CSV, Arrow); no channel may take it.
TIME_COLUMN = "t"
#: Characters a channel name cannot hold (they would break a CSV header).
_FORBIDDEN_NAME_CHARS = ',"\r\n'


def as_float_columns(
    channels: Mapping[str, ArrayLike], t_s: ArrayLike | None
) -> tuple[FloatArray | None, dict[str, FloatArray]]:
    """Validate channels (and per-sample times) and convert them to contiguous float64 arrays.

    Args:
        channels: channel name -> values, one-dimensional, NaN for a missing sample.
        t_s: seconds, one per sample, or None when the batch is timed by ``t0`` and a rate.

    Returns:
        The times (or None) and the channels, in the order given.

    Raises:
        ValueError: no channel, an invalid name, a non-1-D or infinite channel, non-finite
            times, or unequal lengths.
    """
    if not channels:
        raise ValueError("a batch needs at least one channel")
    columns: dict[str, FloatArray] = {}
    for name, values in channels.items():
        if not name or name == TIME_COLUMN or any(c in name for c in _FORBIDDEN_NAME_CHARS):
            raise ValueError(f"invalid channel name {name!r}")
        arr = np.ascontiguousarray(values, dtype=np.float64)
        if arr.ndim != 1:
            raise ValueError(f"channel {name!r} must be one-dimensional, got shape {arr.shape}")
        if np.isinf(arr).any():
            raise ValueError(f"channel {name!r} holds infinite values (use NaN for missing)")
        columns[name] = arr
    lengths = {arr.shape[0] for arr in columns.values()}
    t_arr: FloatArray | None = None
    if t_s is not None:
        t_arr = np.ascontiguousarray(t_s, dtype=np.float64)
        if t_arr.ndim != 1:
            raise ValueError(f"t_s must be one-dimensional, got shape {t_arr.shape}")
        if not np.isfinite(t_arr).all():
            raise ValueError("t_s must be finite")
        lengths.add(t_arr.shape[0])
    if len(lengths) != 1:
        raise ValueError(f"channels (and t_s) have unequal lengths: {sorted(lengths)}")
    return t_arr, columns


def time_params(
    t_arr: FloatArray | None, t0: float | None, sample_rate_hz: float | None
) -> dict[str, float]:
    """``{"t0", "sample_rate_hz"}`` of a batch without per-sample times, else ``{}``.

    Raises:
        ValueError: both or neither timing given, or a non-finite start or non-positive rate.
    """
    if t_arr is not None:
        if t0 is not None or sample_rate_hz is not None:
            raise ValueError("give either t_s or t0 and sample_rate_hz, not both")
        return {}
    if t0 is None or sample_rate_hz is None:
        raise ValueError("give t_s, or both t0 and sample_rate_hz")
    if not (math.isfinite(t0) and math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError("t0 must be finite and sample_rate_hz positive")
    return {"t0": float(t0), "sample_rate_hz": float(sample_rate_hz)}


def query_params(batch_id: str, timing: Mapping[str, float]) -> dict[str, str]:
    """Query string of a table body: the batch id and, when given, ``t0`` and the rate."""
    params = {"batch_id": batch_id}
    # repr gives the shortest string that reads back to the same float.
    params.update({key: repr(value) for key, value in timing.items()})
    return params


def table_columns(
    channels: Mapping[str, ArrayLike],
    t_s: ArrayLike | None,
    t0: float | None,
    sample_rate_hz: float | None,
) -> tuple[list[str], list[FloatArray], dict[str, float]]:
    """Column names and arrays of a table body (``t`` first when given), and the timing."""
    t_arr, columns = as_float_columns(channels, t_s)
    timing = time_params(t_arr, t0, sample_rate_hz)
    names = ([TIME_COLUMN] if t_arr is not None else []) + list(columns)
    arrays = ([t_arr] if t_arr is not None else []) + list(columns.values())
    return names, arrays, timing
