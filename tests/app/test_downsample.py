"""Min/max downsampling for plots, against a plain per-bucket loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.health.downsample import min_max_downsample


def _reference(t: np.ndarray, y: np.ndarray, points: int) -> tuple[list[float], list[float]]:
    """Bucket by bucket: first and last stamps, min and max of the finite values in order."""
    n_buckets = points // 2
    t0, t1 = float(t[0]), float(t[-1])
    t_out: list[float] = []
    y_out: list[float] = []
    for b in range(n_buckets):
        idx = [i for i in range(len(t)) if min(int((t[i] - t0) * (n_buckets / (t1 - t0))), n_buckets - 1) == b]
        if not idx:
            continue
        finite = [i for i in idx if not math.isnan(y[i])]
        if finite:
            i_lo = min(finite, key=lambda i: (y[i], i))
            i_hi = min(finite, key=lambda i: (-y[i], i))
            pair = (y[i_lo], y[i_hi]) if i_lo <= i_hi else (y[i_hi], y[i_lo])
        else:
            pair = (math.nan, math.nan)
        if len(idx) == 1:
            t_out.append(float(t[idx[0]]))
            y_out.append(float(pair[0]))
        else:
            t_out += [float(t[idx[0]]), float(t[idx[-1]])]
            y_out += [float(pair[0]), float(pair[1])]
    return t_out, y_out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_matches_a_plain_loop_over_buckets(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 3000
    t = np.cumsum(rng.uniform(0.001, 0.02, n))
    t[1000:1200] += 5.0 + np.arange(200) * 1e-4  # a gap, then dense samples: empty buckets
    t[1200:] += 5.0
    y = np.cumsum(rng.normal(size=n))
    y[rng.integers(0, n, 100)] = np.nan
    y[2000:2100] = np.nan  # a whole stretch missing: its buckets stay missing
    points = 200
    d = min_max_downsample(t, {"y": y}, points)
    ref_t, ref_y = _reference(t, y, points)
    assert d.reduced
    assert len(d.t_s) <= points
    np.testing.assert_array_equal(d.t_s, ref_t)
    np.testing.assert_array_equal(d.series["y"], ref_y)
    assert np.isnan(d.series["y"]).any()
    assert np.all(np.diff(d.t_s) >= 0)


def test_keeps_every_extreme_and_the_order_they_occur_in() -> None:
    t = np.arange(100_000) * 0.001
    y = np.sin(t)
    y[12_345] = 50.0  # a one-sample spike must survive
    y[67_890] = -50.0
    d = min_max_downsample(t, {"y": y, "ramp": t.copy()}, 500)
    assert len(d.t_s) <= 500
    assert np.nanmax(d.series["y"]) == 50.0 and np.nanmin(d.series["y"]) == -50.0
    # A rising series gives each bucket's min before its max: the output still rises.
    assert np.all(np.diff(d.series["ramp"]) >= 0)
    assert d.series["ramp"][0] == 0.0 and d.series["ramp"][-1] == t[-1]


def test_short_series_come_through_unchanged() -> None:
    t = np.arange(10.0)
    y = np.arange(10.0) ** 2
    d = min_max_downsample(t, {"y": y}, 10)
    assert not d.reduced
    np.testing.assert_array_equal(d.t_s, t)
    np.testing.assert_array_equal(d.series["y"], y)


def test_a_span_wider_than_the_data_uses_fewer_buckets() -> None:
    t = np.arange(1000.0)
    d = min_max_downsample(t, {"y": t}, 100, t_from_s=0.0, t_to_s=1999.0)
    # Half the span holds data: about half of the 50 buckets are filled, two stamps each.
    assert 45 <= len(d.t_s) <= 52
    assert d.t_s[0] == 0.0 and d.t_s[-1] == 999.0


def test_points_below_two_are_refused() -> None:
    with pytest.raises(ValueError, match="points"):
        min_max_downsample(np.arange(5.0), {"y": np.arange(5.0)}, 1)
