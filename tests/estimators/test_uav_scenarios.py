"""The randomized flight generator of the STMMAE validation and the simulator's manoeuvres."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.models.small_uav import SURFACES
from estimators.simulators import uav_scenarios as gen
from estimators.simulators.uav_closed_loop import Manoeuvre, simulate_flight


def test_same_seed_same_scenario_and_categories_differ() -> None:
    assert gen.random_scenario(7, "single") == gen.random_scenario(7, "single")
    assert gen.random_scenario(7, "single") != gen.random_scenario(8, "single")
    assert gen.random_scenario(7, "pair").faults != gen.random_scenario(7, "single").faults
    with pytest.raises(ValueError, match="category"):
        gen.random_scenario(1, "triple")  # type: ignore[arg-type]


def test_draws_stay_in_their_documented_ranges() -> None:
    kinds = set()
    surfaces = set()
    for seed in range(60):
        for category in ("single", "pair"):
            sc = gen.random_scenario(seed, category)
            assert gen.AIRSPEED_RANGE_M_S[0] <= sc.airspeed_m_s <= gen.AIRSPEED_RANGE_M_S[1]
            assert sc.sample_rate_hz in (50.0, 100.0)
            assert len(sc.faults) == (1 if category == "single" else 2)
            trims = gen.trim_deflections_deg(sc.airspeed_m_s)
            for f in sc.faults:
                kinds.add(f.kind)
                surfaces.add(f.surface)
                assert f.end_s - f.start_s >= 10.0 - 1e-9 or category == "pair"
                assert 0.0 < f.start_s < f.end_s <= sc.duration_s
                if f.kind == "stuck":
                    offset = abs(f.position_deg - trims[f.surface])
                    assert gen.MIN_STUCK_OFFSET_DEG - 0.01 <= offset <= 15.01
                    assert abs(f.position_deg) <= gen.SURFACE_LIMIT_DEG
                else:
                    assert 1.5 <= f.amplitude_deg <= 8.0 and 0.5 <= f.period_s <= 4.0
                    assert abs(f.center_deg) + f.amplitude_deg <= gen.SURFACE_LIMIT_DEG + 0.01
            if category == "pair":
                first, second = sc.faults
                assert first.surface != second.surface
                assert 2.0 <= second.start_s - first.start_s <= 8.0
                assert min(first.end_s, second.end_s) - second.start_s >= 5.0 - 0.02
    assert kinds == {"stuck", "square", "sine"} and surfaces == set(SURFACES)
    free = gen.random_scenario(3, "fault_free")
    assert free.faults == () and free.duration_s == 600.0 and free.manoeuvres


def test_a_turn_changes_the_heading_and_a_climb_the_pitch() -> None:
    """A 60 deg heading change over 10 s is flown (the LQR autopilot turns mostly flat: large
    aileron and rudder activity, little bank); a 30 m climb pitches up; with no manoeuvre the
    flight stays level on its heading."""
    turn = (Manoeuvre(2.0, 10.0, heading_change_deg=60.0),)
    _, ch, truth = simulate_flight(20.0, faults=(), manoeuvres=turn, seed=1, noise_scale=0.0)
    _, ch0, level = simulate_flight(20.0, faults=(), seed=1, noise_scale=0.0)
    heading = np.cumsum(truth.states["r"]) * 0.01
    assert heading[-1] == pytest.approx(math.radians(60.0), abs=math.radians(3.0))
    assert np.max(np.abs(ch["cmd_aileron_left"])) > math.radians(5.0)
    assert np.max(np.abs(np.cumsum(level.states["r"]) * 0.01)) < math.radians(0.5)
    assert np.max(np.abs(ch0["cmd_aileron_left"])) < math.radians(0.5)
    climb = (Manoeuvre(2.0, 15.0, altitude_change_m=30.0),)
    _, _, up = simulate_flight(20.0, faults=(), manoeuvres=climb, seed=1, noise_scale=0.0)
    assert np.max(up.states["theta"]) > np.max(level.states["theta"]) + math.radians(3.0)
    assert Manoeuvre(0.0, 4.0, 40.0, -20.0).offsets(2.0) == pytest.approx(
        (math.radians(20.0), -10.0)
    )
    with pytest.raises(ValueError, match="duration"):
        Manoeuvre(0.0, 0.0)
