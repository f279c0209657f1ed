"""Scoring helpers of the STMMAE validation scripts (``scripts/validate_stmmae_random.py``,
``scripts/stmmae_goal_spread.py``): when a stuck fault becomes visible, and the interval and
miss chance the goal spread reports."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import stmmae_goal_spread as spread  # noqa: E402
import validate_stmmae_random as vr  # noqa: E402

from estimators.base import EstimatorEvent  # noqa: E402
from estimators.simulators.uav_closed_loop import SurfaceFault  # noqa: E402
from estimators.simulators.uav_scenarios import FlightScenario  # noqa: E402


def _command(deg: np.ndarray) -> dict[str, np.ndarray]:
    return {"cmd_aileron_right": np.radians(deg)}


def test_a_stuck_fault_is_hidden_while_its_command_stays_near_the_stuck_position() -> None:
    """Stuck at -11 deg while the command ramps from -11 deg by -1 deg/s: visible once the
    command is 2 deg away (2 s after the onset); a command 5 deg away at the onset: visible at
    once; a command that never leaves the position: hidden for the whole fault."""
    t = np.arange(0.0, 20.0, 0.01)
    fault = SurfaceFault("aileron_right", 5.0, 15.0, "stuck", position_deg=-11.0)
    ramp = np.where(t < 5.0, -11.0, -11.0 - (t - 5.0))
    assert vr._hidden_s(t, _command(ramp), fault) == pytest.approx(2.0, abs=0.011)
    far = np.full(t.size, -6.0)
    assert vr._hidden_s(t, _command(far), fault) == pytest.approx(0.0, abs=1e-9)
    near = np.full(t.size, -10.0)
    assert vr._hidden_s(t, _command(near), fault) == pytest.approx(10.0)


def test_wilson_interval_and_the_chance_a_set_misses_a_goal() -> None:
    """Wilson 95 % interval of 0/10 is [0, z^2 / (n + z^2)]; of 5/10 symmetric about 0.5. The
    chance a set of 120 misses 95 % (fewer than 114 right) is the binomial sum, 0 at a true rate
    of 1."""
    z2 = spread.Z95**2
    lo, hi = spread.wilson(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z2 / (10 + z2))
    lo, hi = spread.wilson(5, 10)
    assert lo + hi == pytest.approx(1.0)
    p = 0.959
    want = sum(math.comb(120, k) * p**k * (1 - p) ** (120 - k) for k in range(114))
    assert spread.miss_chance(p, 120, 0.95) == pytest.approx(want, rel=1e-9)
    assert spread.miss_chance(1.0, 120, 0.95) == 0.0
    assert spread.miss_chance(0.99, 40, 0.99) == pytest.approx(1 - 0.99**40)


def _ev(t_s: float, kind: str, component: str, twin: str | None = None) -> EstimatorEvent:
    return EstimatorEvent(
        t_s=t_s, kind=kind, detail={"component": component, "twin_in_fault": twin}
    )


def test_both_halves_in_fault_counts_the_spans_with_only_one_half_faulty() -> None:
    """A right aileron raised at 12 s beside the left (in fault from 10 s), cleared at 15 s:
    one span 12-15 s, with only the left faulty (the right's fault begins at 30 s); the right
    raised again at 31 s with its own fault active: a second span, open to the flight's end,
    both faulty. A detection with no twin in fault opens none."""
    faults = (
        SurfaceFault("aileron_left", 10.0, 40.0, "stuck", position_deg=-8.0),
        SurfaceFault("aileron_right", 30.0, 40.0, "stuck", position_deg=6.0),
    )
    sc = FlightScenario(
        seed=0,
        category="pair",
        duration_s=60.0,
        sample_rate_hz=100.0,
        airspeed_m_s=25.0,
        faults=faults,
        manoeuvres=(),
    )
    events = [
        _ev(10.2, "fault_detected", "aileron_left"),
        _ev(12.0, "fault_detected", "aileron_right", "aileron_left"),
        _ev(15.0, "fault_cleared", "aileron_right", "aileron_left"),
        _ev(31.0, "fault_detected", "aileron_right", "aileron_left"),
    ]
    assert vr.both_halves(sc, events, 60.0) == (2, 1)
    # the right half's fault begins within the span (at 14 s): both faulty
    early = (faults[0], SurfaceFault("aileron_right", 14.0, 40.0, "stuck", position_deg=6.0))
    sc_early = dataclasses.replace(sc, faults=early)
    assert vr.both_halves(sc_early, events, 60.0) == (2, 0)
    assert vr.both_halves(sc, events[:1], 60.0) == (0, 0)
