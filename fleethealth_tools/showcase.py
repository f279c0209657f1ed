"""A small fleet with every actuator kind, for the dashboard's browser tests and screenshots.

``feed_showcase_fleet`` runs the simulator (EMAs, flight controls with the seed paper's surface
faults on every second aircraft, friction drives) as fast as the server takes it, then gives the
first aircraft an SHA/EMA surface flying the DARR seed paper's scenario (hydraulic parameters
drop at 4 s), so that each kind's page has data and a fault to show.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from fleethealth_client import FleetHealthClient

from fleethealth_tools.simulate import SimulationSummary, run_simulation

SHA_EMA_ACTUATOR = "aileron-sha"
SHA_EMA_SECONDS = 7.0
SHA_EMA_BATCH_SAMPLES = 10_000  # 1 s at the simulator's 10 kHz


def feed_sha_ema(url: str, api_key: str, tail: str, *, t0_s: float | None = None, timeout_s: float = 600.0) -> str:
    """Register ``tail``/aileron-sha (kind ``sha_ema``), send the seed paper's scenario and wait
    until it is applied; returns the actuator's status."""
    from estimators.simulators.sha_ema import PAPER_SCENARIO, simulate_sha_ema

    t_s, channels, _truth = simulate_sha_ema(SHA_EMA_SECONDS, faults=PAPER_SCENARIO, seed=4)
    t_s = t_s + (time.time() if t0_s is None else t0_s)
    with FleetHealthClient(url, api_key, timeout=120.0) as client:
        client.create_aircraft(tail)
        client.create_actuator(tail, SHA_EMA_ACTUATOR, kind="sha_ema")
        seq = 0
        for k in range(0, len(t_s), SHA_EMA_BATCH_SAMPLES):
            part = slice(k, k + SHA_EMA_BATCH_SAMPLES)
            ack = client.post_batch(
                tail, SHA_EMA_ACTUATOR, f"showcase-{k}", {c: v[part] for c, v in channels.items()},
                t_s=t_s[part], fmt="arrow",
            )
            seq = int(ack["seq"])
        health = client.wait_applied(tail, SHA_EMA_ACTUATOR, seq, timeout_s=timeout_s)
    return str(health["status"])


def feed_showcase_fleet(
    url: str,
    api_key: str,
    *,
    duration_s: float = 30.0,
    tail_prefix: str = "FH",
    log: Callable[[str], None] = print,
) -> SimulationSummary:
    """Two aircraft, each with an EMA, flight controls and a taxi drive (surface faults on the
    second), and an SHA/EMA surface on the first."""
    summary = run_simulation(
        url, api_key, aircraft=2, actuators_per_aircraft=1, duration_s=duration_s, realtime=False,
        flight_controls=True, friction_drives=True, faults="paper", tail_prefix=tail_prefix,
        ready_timeout_s=600.0, log=log,
    )
    status = feed_sha_ema(url, api_key, f"{tail_prefix}-001")
    log(f"showcase: {tail_prefix}-001/{SHA_EMA_ACTUATOR} sha_ema scenario applied, status {status}")
    return summary
