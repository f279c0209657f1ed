"""Small checks shared by the estimators: configuration numbers, JSON-safe floats, channel
blocks of a batch."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimators.base import Batch, ConfigError, EstimatorError, FloatArray


def is_number(value: Any) -> bool:
    """An int or float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def finite(name: str, value: Any) -> float:
    """``value`` as a finite float; :class:`ConfigError` naming ``name`` otherwise."""
    if not is_number(value) or not math.isfinite(float(value)):
        raise ConfigError(f"{name}: expected a finite number, got {value!r}")
    return float(value)


def positive(name: str, value: Any) -> float:
    v = finite(name, value)
    if v <= 0.0:
        raise ConfigError(f"{name}: expected a positive number, got {value!r}")
    return v


def non_negative(name: str, value: Any) -> float:
    v = finite(name, value)
    if v < 0.0:
        raise ConfigError(f"{name}: expected a number >= 0, got {value!r}")
    return v


def finite_or_none(value: float) -> float | None:
    """The float, or None when it is NaN or infinite (JSON has neither)."""
    v = float(value)
    return v if math.isfinite(v) else None


def channel_block(batch: Batch, names: Sequence[str], n: int) -> FloatArray:
    """The named channels of ``batch`` as rows of an (len(names), n) float64 array."""
    block = np.empty((len(names), n))
    for i, name in enumerate(names):
        try:
            values = batch.channels[name]
        except KeyError:
            raise EstimatorError(f"batch has no channel {name!r}") from None
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (n,):
            raise EstimatorError(f"channel {name!r} has shape {arr.shape}, expected ({n},)")
        block[i] = arr
    return block
