"""Estimator kinds and actuator kinds known to the service.

An actuator kind names the channels its telemetry carries and the estimators attached by default.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from estimators import darr_fekf, deterioration_ekf, fakf, stmmae
from estimators.base import EstimatorConfigModel, EstimatorKind

ESTIMATORS: dict[str, EstimatorKind] = {
    darr_fekf.NAME: darr_fekf,
    deterioration_ekf.NAME: deterioration_ekf,
    fakf.NAME: fakf,
    stmmae.NAME: stmmae,
}


@dataclass(frozen=True)
class ActuatorKind:
    """Defaults for one kind of actuator.

    Attributes:
        name: kind name used in the API.
        description: one line for the docs and the API.
        channels: channel names its telemetry carries by default.
        default_estimators: estimator name -> raw config attached when none are given.
    """

    name: str
    description: str
    channels: tuple[str, ...]
    default_estimators: dict[str, dict[str, Any]] = field(default_factory=dict)


ACTUATOR_KINDS: dict[str, ActuatorKind] = {
    "sha_ema": ActuatorKind(
        name="sha_ema",
        description="SHA/EMA redundant surface (w rad/s, f_c N, v m/s, f_e N, f_h N, v_p m/s, "
        "p_l Pa; inputs x_v m, u_a V) -> DARR residuals, fault isolation and FEKF",
        channels=("w", "f_c", "v", "f_e", "f_h", "v_p", "p_l", "x_v", "u_a"),
        default_estimators={"darr_fekf": {}},
    ),
    "friction_drive": ActuatorKind(
        name="friction_drive",
        description="Roller-on-tire friction drive (motor current A, motor and wheel speeds "
        "rad/s) -> contact deterioration EKF and RUL",
        channels=("current", "motor_speed", "wheel_speed"),
        # The estimator's own defaults carry the prognosis tuning (a random walk on the wear rate
        # relative to its size, m_walk_rel, independent of the sample rate). The kind states the
        # nominal 1 kHz period so that rounded absolute time stamps do not jitter the
        # discretization.
        default_estimators={"deterioration_ekf": {"sample_period_s": 0.001}},
    ),
    "ema_voltage": ActuatorKind(
        name="ema_voltage",
        description="Electro-mechanical actuator, motor voltage monitoring (current, voltage) -> FAKF",
        channels=("current", "voltage"),
        default_estimators={"fakf": {}},
    ),
    "flight_controls": ActuatorKind(
        name="flight_controls",
        description="Small-UAV control surfaces (rates rad/s, angles rad, airspeed m/s, commands "
        "rad, throttle 0..1) -> STMMAE fault isolation",
        channels=(
            "p",
            "q",
            "r",
            "alpha",
            "beta",
            "airspeed",
            "cmd_aileron_left",
            "cmd_aileron_right",
            "cmd_elevator_left",
            "cmd_elevator_right",
            "cmd_rudder",
            "cmd_throttle",
        ),
        default_estimators={"stmmae": {}},
    ),
}


def get_estimator(name: str) -> EstimatorKind:
    """The estimator kind registered under ``name`` (KeyError if none)."""
    return ESTIMATORS[name]


def config_model(name: str) -> type[EstimatorConfigModel]:
    """The public configuration model of estimator ``name`` (KeyError if none)."""
    return ESTIMATORS[name].CONFIG_MODEL
