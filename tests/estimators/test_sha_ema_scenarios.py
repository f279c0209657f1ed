"""Sensor faults and the randomized scenario generator of the SHA/EMA plant."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.simulators.sha_ema_scenarios import (
    SensorFault,
    apply_sensor_faults,
    generate_scenarios,
)


def _stream():
    t = np.arange(1000) * 1e-3
    rng = np.random.default_rng(0)
    return t, {"p_l": 1e6 + 1e4 * rng.standard_normal(1000), "v": np.sin(t)}


def test_sensor_faults_act_from_their_onset_only() -> None:
    t, ch = _stream()
    out = apply_sensor_faults(
        t,
        ch,
        [
            SensorFault("p_l", "bias", 0.5, 2e5),
            SensorFault("v", "drift", 0.25, 3.0),
        ],
    )
    before = t < 0.5
    np.testing.assert_array_equal(out["p_l"][before], ch["p_l"][before])
    np.testing.assert_allclose(out["p_l"][~before] - ch["p_l"][~before], 2e5)
    on = t >= 0.25
    np.testing.assert_allclose(out["v"][on] - ch["v"][on], 3.0 * (t[on] - 0.25), atol=1e-12)
    assert out["p_l"] is not ch["p_l"]  # inputs unchanged


def test_stuck_holds_the_reading_and_noise_adds_variance() -> None:
    t, ch = _stream()
    stuck = apply_sensor_faults(t, ch, [SensorFault("p_l", "stuck", 0.3)])["p_l"]
    assert np.all(stuck[300:] == ch["p_l"][300])
    noisy = apply_sensor_faults(t, ch, [SensorFault("p_l", "noise", 0.0, 4.0)], seed=1)["p_l"]
    added = np.std(noisy - ch["p_l"])
    assert added == pytest.approx(4.0 * math.sqrt(5e-2) * 1e5, rel=0.1)
    with pytest.raises(ValueError, match="channel"):
        apply_sensor_faults(t, ch, [SensorFault("zz", "bias", 0.0, 1.0)])


def test_generator_is_reproducible_and_covers_every_condition() -> None:
    a = generate_scenarios(3)
    b = generate_scenarios(3)
    assert a == b and a != generate_scenarios(4)
    conditions = {s.condition for s in a}
    assert conditions == {
        "fault_free",
        "parameter",
        "sensor_bias",
        "sensor_drift",
        "sensor_stuck",
        "sensor_noise",
        "calibration_parameter",
        "calibration_sensor",
    }
    for s in a:
        if s.condition.startswith("calibration"):
            assert s.onset_s < 3.0
        elif s.condition != "fault_free":
            assert 3.5 <= s.onset_s <= s.duration_s - 3.0 + 1e-9
        assert (s.family == "none") == (not s.true_members)
