"""Min/max downsampling of time series for plots.

A chart ``points`` pixels wide cannot show more than one value range per pixel column. Splitting
the time span into ``points // 2`` equal buckets and keeping, per bucket and series, its minimum
and its maximum (in the order they occur) keeps every peak and every trough a line plot would
draw, so the downsampled line covers exactly the pixels of the full one. Each bucket gives two
time stamps, its first and its last sample's, shared by every series: a value is drawn at most one
bucket width (about one pixel) away from where it occurred.

Missing values (NaN) are ignored; a bucket whose values of one series are all missing stays
missing for that series, so gaps remain gaps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.base import FloatArray


@dataclass(frozen=True)
class Downsampled:
    """The series to draw, on one shared time axis.

    Attributes:
        t_s: time stamps, increasing.
        series: name -> values at ``t_s`` (NaN where missing).
        reduced: True when buckets replaced the samples, False when the samples came through.
    """

    t_s: FloatArray
    series: dict[str, FloatArray]
    reduced: bool


def bucket_starts(t_s: FloatArray, t_from_s: float, t_to_s: float, n_buckets: int) -> np.ndarray:
    """Index of the first sample of each non-empty bucket, for increasing ``t_s`` inside
    ``[t_from_s, t_to_s]`` split into ``n_buckets`` equal spans."""
    span = t_to_s - t_from_s
    if span <= 0.0:
        return np.zeros(1, dtype=np.int64)
    bucket = np.clip(((t_s - t_from_s) * (n_buckets / span)).astype(np.int64), 0, n_buckets - 1)
    return np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])


def _first_index_of(mask: np.ndarray, starts: np.ndarray, n: int) -> np.ndarray:
    """Per bucket, the index of its first sample where ``mask`` holds (``n`` if none)."""
    idx = np.where(mask, np.arange(n), n)
    return np.minimum.reduceat(idx, starts)


def _min_max_in_order(values: FloatArray, starts: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """Per bucket, (first, second) of its minimum and maximum in the order they occur."""
    n = len(values)
    counts = np.diff(np.r_[starts, n])
    lo = np.fmin.reduceat(values, starts)  # fmin skips NaN unless the bucket has nothing else
    hi = np.fmax.reduceat(values, starts)
    i_lo = _first_index_of(values == np.repeat(lo, counts), starts, n)
    i_hi = _first_index_of(values == np.repeat(hi, counts), starts, n)
    lo_first = i_lo <= i_hi
    return np.where(lo_first, lo, hi), np.where(lo_first, hi, lo)


def min_max_downsample(
    t_s: FloatArray,
    series: dict[str, FloatArray],
    points: int,
    t_from_s: float | None = None,
    t_to_s: float | None = None,
) -> Downsampled:
    """At most ``points`` samples that draw like ``series`` at ``points`` pixels wide.

    Args:
        t_s: increasing sample times, shape (n,).
        series: name -> values, each of shape (n,).
        points: the chart's width in pixels (at least 2).
        t_from_s: start of the drawn span (default the first sample).
        t_to_s: end of the drawn span (default the last sample).

    Returns:
        The samples themselves when there are no more than ``points``; otherwise, per non-empty
        bucket of the span, its first and last time stamps with each series' minimum and maximum
        in their order of occurrence (one stamp and one value for a bucket of one sample).
    """
    if points < 2:
        raise ValueError("points must be at least 2")
    n = len(t_s)
    if n <= points:
        return Downsampled(t_s=t_s, series=dict(series), reduced=False)
    t_from = float(t_s[0]) if t_from_s is None else t_from_s
    t_to = float(t_s[-1]) if t_to_s is None else t_to_s
    starts = bucket_starts(t_s, t_from, t_to, points // 2)
    ends = np.r_[starts[1:], n] - 1
    single = starts == ends
    # Two stamps per bucket (its first and last sample), one for a bucket of one sample.
    keep = np.ones(2 * len(starts), dtype=bool)
    keep[1::2] = ~single
    t_out = np.empty(2 * len(starts))
    t_out[0::2] = t_s[starts]
    t_out[1::2] = t_s[ends]
    out: dict[str, FloatArray] = {}
    for name, values in series.items():
        first, second = _min_max_in_order(np.asarray(values, dtype=np.float64), starts)
        v = np.empty(2 * len(starts))
        v[0::2] = first
        v[1::2] = second
        out[name] = v[keep]
    return Downsampled(t_s=t_out[keep], series=out, reduced=True)
