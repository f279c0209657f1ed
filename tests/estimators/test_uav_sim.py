"""The small-UAV reference model and its closed-loop simulator (the ground truth of stmmae)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.models import small_uav as uav
from estimators.registry import ACTUATOR_KINDS
from estimators.simulators.uav_closed_loop import (
    CHANNELS,
    PAPER_FAULT_SCHEDULE,
    SENSOR_VAR,
    SurfaceFault,
    simulate_flight,
)


def test_trim_is_an_equilibrium() -> None:
    prm = uav.AerosondeParams()
    trim = uav.trim_level(prm, 25.0)
    zd = uav.reduced_derivatives(prm, trim.reduced_state, trim.inputs)
    # Newton stops at steps below 1e-13: residual rates are at round-off level
    assert np.max(np.abs(zd)) < 1e-9
    assert 0.0 < trim.alpha_rad < 0.2 and 0.0 < trim.throttle < 1.0


def test_discrete_model_predicts_the_nonlinear_step() -> None:
    """One step of the reference model against RK4 on the nonlinear equations from a small
    perturbation of trim: the difference is second order in the perturbation."""
    prm = uav.AerosondeParams()
    model = uav.reference_model(0.01, 25.0)
    f, g = np.array(model["F"]), np.array(model["G"])
    x_trim, u_trim = np.array(model["x_trim"]), np.array(model["u_trim"])
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1e-2):
        dz = scale * rng.standard_normal(8) * np.array([1.0, 0.1, 0.1, 1, 1, 1, 0.1, 0.1])
        du = scale * rng.standard_normal(6) * 0.1
        z0 = x_trim + dz
        x = uav.full_from_reduced(z0)
        d = u_trim + du
        # ten RK4 substeps of 1 ms: integration error far below the linearization error
        for _ in range(10):
            k1 = uav.derivatives(prm, x, d)
            k2 = uav.derivatives(prm, x + 0.0005 * k1, d)
            k3 = uav.derivatives(prm, x + 0.0005 * k2, d)
            k4 = uav.derivatives(prm, x + 0.001 * k3, d)
            x = x + 0.001 / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        va, alpha, beta = uav.air_data(x)
        z1 = np.array([va, alpha, beta, x[9], x[10], x[11], x[6], x[7]])
        predicted = x_trim + f @ dz + g @ du
        step = np.abs(z1 - z0)
        err = np.abs(z1 - predicted)
        # second order: the error shrinks ~100x when the perturbation shrinks 10x; bound it
        # by a fraction of the step itself
        assert np.all(err <= 0.05 * step + 1e-9 * (scale / 1e-3) ** 2 * 10)


def test_split_surfaces_are_distinguishable() -> None:
    """Left and right halves must not have identical input columns (else no isolation)."""
    g = np.array(uav.reference_model()["G"])
    for left, right in ((0, 1), (2, 3)):
        assert not np.allclose(g[:, left], g[:, right])
        # the main effect is shared: the roll (aileron) or pitch (elevator) rows are equal
    assert g[3, 0] == pytest.approx(g[3, 1], rel=1e-6)  # p row, ailerons
    assert g[4, 2] == pytest.approx(g[4, 3], rel=1e-6)  # q row, elevators


def test_channels_match_the_registry_kind() -> None:
    assert set(CHANNELS) == set(ACTUATOR_KINDS["flight_controls"].channels)


def test_fault_free_flight_holds_trim() -> None:
    t, ch, truth = simulate_flight(20.0, faults=(), seed=0, noise_scale=0.0)
    assert t.shape == (2000,) and np.all(np.diff(t) > 0)
    assert np.all(truth.faulty_surface == -1)
    for name, value in zip(uav.STATES, truth.trim.reduced_state, strict=True):
        # the flight starts exactly at trim and nothing perturbs it
        np.testing.assert_allclose(truth.states[name], value, atol=1e-6)
    np.testing.assert_allclose(ch["airspeed"], 25.0, atol=1e-6)


def test_faults_replace_the_surface_deflection() -> None:
    faults = (
        SurfaceFault("aileron_left", 2.0, 6.0, "stuck", position_deg=-12.0),
        SurfaceFault("elevator_right", 8.0, 12.0, "square", center_deg=4.0, amplitude_deg=2.0),
        SurfaceFault("rudder", 13.0, 16.0, "sine", center_deg=1.0, amplitude_deg=3.0),
    )
    t, ch, truth = simulate_flight(18.0, faults=faults, seed=1)
    d = {s: np.degrees(v) for s, v in truth.deflections_rad.items()}
    stuck = (t >= 2.0) & (t < 6.0)
    np.testing.assert_allclose(d["aileron_left"][stuck], -12.0, atol=1e-12)
    sq = (t >= 8.0) & (t < 12.0)
    assert set(np.round(d["elevator_right"][sq], 9)) == {2.0, 6.0}
    first_half = (t >= 8.0) & (t < 9.0)
    np.testing.assert_allclose(d["elevator_right"][first_half], 6.0, atol=1e-12)
    sine = (t >= 13.0) & (t < 16.0)
    expected = 1.0 + 3.0 * np.sin(2 * np.pi * (t[sine] - 13.0) / 2.0)
    np.testing.assert_allclose(d["rudder"][sine], expected, atol=1e-9)
    assert np.all(truth.faulty_surface[stuck] == uav.SURFACES.index("aileron_left"))
    assert np.all(truth.faulty_surface[(t >= 6.0) & (t < 8.0)] == -1)
    # the autopilot compensates the stuck left aileron with the aileron command (both halves)
    np.testing.assert_array_equal(ch["cmd_aileron_left"], ch["cmd_aileron_right"])
    assert np.mean(np.degrees(ch["cmd_aileron_left"][(t > 4.0) & (t < 6.0)])) > 5.0
    # after the fault the left aileron follows its command again (servo lag 20 ms)
    late = (t > 7.0) & (t < 8.0)
    np.testing.assert_allclose(
        truth.deflections_rad["aileron_left"][late], ch["cmd_aileron_left"][late], atol=2e-3
    )
    # wings stay level within a few degrees through the fault
    assert np.max(np.abs(truth.states["phi"])) < math.radians(10.0)


def test_sensor_noise_has_the_paper_variances() -> None:
    t, ch, truth = simulate_flight(100.0, faults=(), seed=3)
    for name, var in SENSOR_VAR.items():
        err = ch[name] - truth.states[name]
        # sample variance of 10,000 Gaussian samples: relative std sqrt(2/n) = 1.4 %, 5 sigma
        assert np.var(err) == pytest.approx(var, rel=0.07)
        assert abs(np.mean(err)) < 5 * math.sqrt(var / len(t))


def test_seed_determines_the_flight() -> None:
    a = simulate_flight(3.0, faults=PAPER_FAULT_SCHEDULE, seed=5)
    b = simulate_flight(3.0, faults=PAPER_FAULT_SCHEDULE, seed=5)
    c = simulate_flight(3.0, faults=PAPER_FAULT_SCHEDULE, seed=6)
    for name in CHANNELS:
        np.testing.assert_array_equal(a[1][name], b[1][name])
    assert not np.array_equal(a[1]["p"], c[1]["p"])


def test_paper_schedule() -> None:
    surfaces = [f.surface for f in PAPER_FAULT_SCHEDULE]
    assert surfaces == [
        "aileron_left",
        "aileron_right",
        "rudder",
        "elevator_left",
        "elevator_right",
    ]
    assert [(f.start_s, f.end_s) for f in PAPER_FAULT_SCHEDULE] == [
        (10.0, 40.0),
        (70.0, 100.0),
        (130.0, 160.0),
        (190.0, 220.0),
        (250.0, 280.0),
    ]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"surface": "flap", "start_s": 1.0, "end_s": 2.0},
        {"surface": "rudder", "start_s": 2.0, "end_s": 2.0},
        {"surface": "rudder", "start_s": 1.0, "end_s": 2.0, "kind": "ramp"},
        {"surface": "rudder", "start_s": 1.0, "end_s": 2.0, "kind": "square", "period_s": 0.0},
    ],
)
def test_bad_fault_specs_are_refused(kwargs) -> None:
    with pytest.raises(ValueError):
        SurfaceFault(**kwargs)
