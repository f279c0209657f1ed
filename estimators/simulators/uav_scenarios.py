"""Randomized flights with control-surface faults for validating ``stmmae`` beyond fixed schedules.

:func:`random_scenario` draws one flight from a seeded generator: cruise airspeed, sample rate,
manoeuvres (coordinated turns, climbs and descents), and, by category, no fault, one fault, or two
overlapping faults of different surfaces. Stuck positions are at least ``MIN_STUCK_OFFSET_DEG``
from the surface's trim; oscillations are square or sine waves with random centre, amplitude and
period. The draws are listed in ``docs/methods-stmmae.md`` ("Randomized validation"); the same
seed always gives the same scenario.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimators.models import small_uav as uav
from estimators.simulators.uav_closed_loop import (
    FlightTruth,
    FloatArray,
    Manoeuvre,
    SurfaceFault,
    simulate_flight,
)

Category = Literal["fault_free", "single", "pair"]
CATEGORIES: tuple[Category, ...] = ("fault_free", "single", "pair")

AIRSPEED_RANGE_M_S = (22.0, 32.0)
SAMPLE_RATES_HZ = (100.0, 100.0, 100.0, 50.0)  # drawn uniformly: 50 Hz in a quarter of flights
MIN_STUCK_OFFSET_DEG = 2.0
MAX_STUCK_OFFSET_DEG = 15.0
OSCILLATION_AMPLITUDE_DEG = (1.5, 8.0)
OSCILLATION_PERIOD_S = (0.5, 4.0)
OSCILLATION_CENTER_OFFSET_DEG = 3.0
FAULT_LENGTH_S = (10.0, 25.0)
SECOND_FAULT_DELAY_S = (2.0, 8.0)
SURFACE_LIMIT_DEG = 25.0  # fault positions stay inside the surfaces' travel (30 deg)
DURATION_S: dict[str, float] = {"fault_free": 600.0, "single": 80.0, "pair": 90.0}


@dataclass(frozen=True)
class FlightScenario:
    """One randomized flight.

    Attributes:
        seed: the generator seed it was drawn from (also the sensor-noise seed).
        category: ``fault_free``, ``single`` or ``pair``.
        duration_s: flight length, s.
        sample_rate_hz: sensor and autopilot rate.
        airspeed_m_s: cruise (trim) airspeed; the estimator's model is linearized there.
        faults: the surface faults, in onset order.
        manoeuvres: heading/altitude reference changes.
    """

    seed: int
    category: Category
    duration_s: float
    sample_rate_hz: float
    airspeed_m_s: float
    faults: tuple[SurfaceFault, ...]
    manoeuvres: tuple[Manoeuvre, ...]

    def simulate(
        self, noise_scale: float = 1.0
    ) -> tuple[FloatArray, dict[str, FloatArray], FlightTruth]:
        """Fly it (``uav_closed_loop.simulate_flight``; ``noise_scale`` multiplies the sensor
        noise standard deviations)."""
        return simulate_flight(
            self.duration_s,
            sample_rate_hz=self.sample_rate_hz,
            faults=self.faults,
            seed=self.seed,
            airspeed_m_s=self.airspeed_m_s,
            manoeuvres=self.manoeuvres,
            noise_scale=noise_scale,
        )


def trim_deflections_deg(airspeed_m_s: float) -> dict[str, float]:
    """Each surface's trim deflection (deg) at a level-flight airspeed."""
    trim = uav.trim_level(uav.AerosondeParams(), airspeed_m_s)
    return {s: math.degrees(float(trim.inputs[i])) for i, s in enumerate(uav.SURFACES)}


def _fault(
    rng: np.random.Generator, surface: str, trim_deg: float, start_s: float, end_s: float
) -> SurfaceFault:
    draw = rng.uniform()
    lim = SURFACE_LIMIT_DEG
    if draw < 0.5:
        offset = rng.uniform(MIN_STUCK_OFFSET_DEG, MAX_STUCK_OFFSET_DEG)
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        pos = trim_deg + sign * offset
        if abs(pos) > lim:  # keep inside the travel: stuck on the other side of trim instead
            pos = trim_deg - sign * offset
        return SurfaceFault(surface, start_s, end_s, "stuck", position_deg=round(pos, 2))
    kind: Literal["square", "sine"] = "square" if draw < 0.75 else "sine"
    amplitude = rng.uniform(*OSCILLATION_AMPLITUDE_DEG)
    center = trim_deg + rng.uniform(-OSCILLATION_CENTER_OFFSET_DEG, OSCILLATION_CENTER_OFFSET_DEG)
    center = min(max(center, -lim + amplitude), lim - amplitude)
    return SurfaceFault(
        surface,
        start_s,
        end_s,
        kind,
        center_deg=round(center, 2),
        amplitude_deg=round(amplitude, 2),
        period_s=round(rng.uniform(*OSCILLATION_PERIOD_S), 2),
    )


def _manoeuvres(rng: np.random.Generator, duration_s: float) -> tuple[Manoeuvre, ...]:
    """Turns of 30-120 deg at 3-8 deg/s and climbs/descents of 10-50 m over 10-30 s, one per
    40 s of flight on average, at random times (they may overlap each other and the faults)."""
    count = int(rng.poisson(duration_s / 40.0))
    out = []
    for _ in range(count):
        start = rng.uniform(5.0, max(duration_s - 20.0, 6.0))
        if rng.uniform() < 0.6:
            change = rng.uniform(30.0, 120.0) * (1.0 if rng.uniform() < 0.5 else -1.0)
            rate = rng.uniform(3.0, 8.0)
            out.append(Manoeuvre(start, abs(change) / rate, heading_change_deg=round(change, 1)))
        else:
            change = rng.uniform(10.0, 50.0) * (1.0 if rng.uniform() < 0.5 else -1.0)
            out.append(
                Manoeuvre(start, rng.uniform(10.0, 30.0), altitude_change_m=round(change, 1))
            )
    return tuple(sorted(out, key=lambda m: m.start_s))


def random_scenario(
    seed: int, category: Category, duration_s: float | None = None
) -> FlightScenario:
    """Draw one flight of a category from ``numpy.random.default_rng(seed)``.

    Args:
        seed: generator seed (also the flight's sensor-noise seed).
        category: ``fault_free``, ``single`` (one fault) or ``pair`` (two faults of different
            surfaces, the second starting 2-8 s after the first while the first lasts, so the
            two overlap for at least 5 s).
        duration_s: flight length (default :data:`DURATION_S` of the category).
    """
    if category not in CATEGORIES:
        raise ValueError(f"category: expected one of {CATEGORIES}, got {category!r}")
    rng = np.random.default_rng([seed, CATEGORIES.index(category)])
    duration = DURATION_S[category] if duration_s is None else float(duration_s)
    airspeed = round(float(rng.uniform(*AIRSPEED_RANGE_M_S)) * 2.0) / 2.0
    rate = float(SAMPLE_RATES_HZ[int(rng.integers(len(SAMPLE_RATES_HZ)))])
    trims = trim_deflections_deg(airspeed)
    manoeuvres = _manoeuvres(rng, duration)
    faults: list[SurfaceFault] = []
    if category != "fault_free":
        surfaces = list(uav.SURFACES)
        first = surfaces[int(rng.integers(len(surfaces)))]
        start = rng.uniform(15.0, duration - 40.0)
        end = start + rng.uniform(*FAULT_LENGTH_S)
        if category == "pair":
            end = max(end, start + SECOND_FAULT_DELAY_S[1] + 5.0)
        faults.append(_fault(rng, first, trims[first], round(start, 2), round(end, 2)))
        if category == "pair":
            others = [s for s in surfaces if s != first]
            second = others[int(rng.integers(len(others)))]
            start2 = start + rng.uniform(*SECOND_FAULT_DELAY_S)
            end2 = min(start2 + rng.uniform(*FAULT_LENGTH_S), duration - 5.0)
            faults.append(_fault(rng, second, trims[second], round(start2, 2), round(end2, 2)))
    return FlightScenario(
        seed=seed,
        category=category,
        duration_s=duration,
        sample_rate_hz=rate,
        airspeed_m_s=airspeed,
        faults=tuple(faults),
        manoeuvres=manoeuvres,
    )


def describe(fault: SurfaceFault) -> str:
    """Short human description of a fault."""
    if fault.kind == "stuck":
        what = f"stuck at {fault.position_deg:+.1f} deg"
    else:
        lo, hi = fault.center_deg - fault.amplitude_deg, fault.center_deg + fault.amplitude_deg
        what = f"{fault.kind} {lo:+.1f}..{hi:+.1f} deg, period {fault.period_s:g} s"
    return f"{fault.surface} {what} ({fault.start_s:g}-{fault.end_s:g} s)"
