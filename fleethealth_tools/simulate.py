"""``fleethealth simulate``: a fleet of simulated EMAs streaming telemetry to a running server.

Each simulated actuator runs the reference EMA plant of ``estimators.simulators.ema_motor``
work cycle after work cycle (one call of ``simulate_ema`` per cycle) and sends the samples in
batches of ``batch_seconds``. Stream time is absolute (POSIX seconds) and continues across batches,
cycles and restarts: an actuator that already has data resumes after its last sample.

Some actuators degrade: their ball screw binds. A severity grows from 0 to 1 over
``degrade_over_s`` seconds of stream time (nothing in the first quarter, then linearly) and the
plant's viscous friction grows with it, up to :data:`FRICTION_GROWTH` times its nominal value. The
motor then draws more current for the same motion, the drive saturates and lags its command, and
the current-to-voltage relation the FAKF identified on the healthy start no longer holds: the
innovation ratio and NIS rise, and the FAKF health goes to watch (about half way) and alert (about
three quarters of the way). Nothing but the plant's physics changes; there is no status label.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import httpx
import numpy as np
from fleethealth_client import (
    BATCH_FORMATS,
    ApiError,
    FleetHealthClient,
    FrameStreamer,
    StreamRefused,
)

from fleethealth_tools.readiness import KernelProgress, wait_for_server

DEFAULT_URL = "http://127.0.0.1:8000"
ACTUATOR_KIND = "ema_voltage"
FLIGHT_KIND = "flight_controls"
CHANNELS = ("current", "voltage")
#: Actuator slots per aircraft; more actuators than names get ``ema-<n>``.
ACTUATOR_NAMES = ("ema-left", "ema-right", "ema-rudder", "ema-nose")
#: Length of one work cycle of the plant (the FLEA runs last about 30 s).
CYCLE_S = 30.0
#: Plant parameter that degrades: viscous friction B of eq. 14 (N m s/rad).
FRICTION_PARAMETER = "damping_nm_s_rad"
#: Friction at full severity over nominal friction (a binding screw; the drive saturates).
FRICTION_GROWTH = 60.0
#: Fraction of ``degrade_over_s`` before the fault starts (the FAKF identifies on healthy data).
ONSET_FRACTION = 0.25

Log = Callable[[str], Any]


@dataclass
class SimulationSummary:
    """What a simulation run did."""

    aircraft: list[str] = field(default_factory=list)
    actuators: list[tuple[str, str]] = field(default_factory=list)
    batches_sent: int = 0
    samples_sent: int = 0
    errors: int = 0
    stream_seconds: float = 0.0


@dataclass
class _Stream:
    """One simulated actuator: its identity, load, degradation and the time of its next sample."""

    tail: str
    actuator_id: str
    load_lbs: float
    degrade_over_s: float | None
    seed: int
    t_next_s: float
    t_begin_s: float
    cycle_index: int = 0
    kind: str = ACTUATOR_KIND
    inject_faults: bool = False
    wear_rate: float = 0.0
    pending_t: np.ndarray | None = None
    pending: dict[str, np.ndarray] | None = None
    pending_pos: int = 0


def _load_simulator() -> Callable[..., Any]:
    from estimators.simulators.ema_motor import simulate_ema

    return simulate_ema


def _nominal_friction() -> float:
    from estimators.simulators.ema_motor import EmaParams

    return float(getattr(EmaParams(), FRICTION_PARAMETER))


def severity_at(elapsed_s: float, degrade_over_s: float) -> float:
    """Fault severity in [0, 1]: 0 until ``ONSET_FRACTION * degrade_over_s``, then linear."""
    if degrade_over_s <= 0:
        return 1.0
    onset_s = ONSET_FRACTION * degrade_over_s
    return float(min(1.0, max(0.0, (elapsed_s - onset_s) / (degrade_over_s - onset_s))))


class _Fleet:
    """Generates each stream's samples cycle by cycle and cuts them into batches."""

    def __init__(
        self,
        streams: list[_Stream],
        sample_rate_hz: float,
        simulate: Callable[..., Any],
        nominal_friction: float,
    ) -> None:
        self.streams = streams
        self.sample_rate_hz = sample_rate_hz
        self.simulate = simulate
        self.nominal_friction = nominal_friction

    def friction_at(self, stream: _Stream) -> float:
        if stream.degrade_over_s is None:
            return self.nominal_friction
        severity = severity_at(stream.t_next_s - stream.t_begin_s, stream.degrade_over_s)
        return self.nominal_friction * (1.0 + severity * (FRICTION_GROWTH - 1.0))

    def _next_cycle(self, stream: _Stream) -> None:
        run = self.simulate(
            CYCLE_S,
            self.sample_rate_hz,
            stream.load_lbs,
            stream.seed * 1_000_003 + stream.cycle_index,
            **{FRICTION_PARAMETER: self.friction_at(stream)},
        )
        stream.cycle_index += 1
        n = len(run.t_s)
        # Absolute times continue the stream: sample k of the cycle is k periods after t_next.
        stream.pending_t = stream.t_next_s + np.arange(n, dtype=np.float64) / self.sample_rate_hz
        stream.pending = {
            "current": np.asarray(run.current_a, dtype=np.float64),
            "voltage": np.asarray(run.voltage_measured_v, dtype=np.float64),
        }
        stream.pending_pos = 0

    def next_batch(
        self, stream: _Stream, n_samples: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The next ``n_samples`` of a stream (may span two plant cycles)."""
        return _take(stream, n_samples, self.sample_rate_hz, lambda: self._next_cycle(stream))


#: Stream seconds of one simulated flight of a flight-controls unit (the plant restarts from trim).
FLIGHT_CHUNK_S = 300.0
#: The flight-controls reference model is discrete at 100 Hz; its telemetry uses that rate.
FLIGHT_RATE_HZ = 100.0
FAULT_MODES = ("none", "paper", "random")


def random_fault_schedule(rng: np.random.Generator, duration_s: float) -> tuple[Any, ...]:
    """Two surface faults at random times in a flight: a stuck surface and an oscillating one,
    each 10-30 s long, on two different surfaces, with random positions and swings."""
    from estimators.models.small_uav import SURFACES
    from estimators.simulators.uav_closed_loop import SurfaceFault

    first, second = rng.choice(len(SURFACES), size=2, replace=False)
    half = duration_s / 2.0
    out = []
    for k, surface in enumerate((SURFACES[first], SURFACES[second])):
        length = float(rng.uniform(10.0, 30.0))
        start = float(k * half + rng.uniform(20.0, max(21.0, half - length - 20.0)))
        limit = 3.0 if surface == "rudder" else 12.0
        if k == 0:
            pos = float(np.round(rng.uniform(2.0, limit) * rng.choice([-1.0, 1.0]), 1))
            out.append(SurfaceFault(surface, start, start + length, "stuck", position_deg=pos))
        else:
            amp = float(np.round(rng.uniform(2.0, limit), 1))
            out.append(
                SurfaceFault(
                    surface,
                    start,
                    start + length,
                    "square",
                    amplitude_deg=amp,
                    period_s=float(np.round(rng.uniform(1.0, 3.0), 1)),
                )
            )
    return tuple(out)


class _Flights:
    """Flight-controls telemetry: closed-loop flights of :data:`FLIGHT_CHUNK_S` seconds with the
    stream's fault schedule, cut into batches."""

    def __init__(self, faults_for: Callable[[_Stream, int], tuple[Any, ...]]) -> None:
        self.faults_for = faults_for

    def _next_chunk(self, stream: _Stream) -> None:
        from estimators.simulators.uav_closed_loop import simulate_flight

        faults = self.faults_for(stream, stream.cycle_index)
        t, channels, _truth = simulate_flight(
            FLIGHT_CHUNK_S,
            sample_rate_hz=FLIGHT_RATE_HZ,
            faults=faults,
            seed=stream.seed * 1_000_003 + stream.cycle_index,
        )
        stream.cycle_index += 1
        stream.pending_t = stream.t_next_s + np.arange(len(t), dtype=np.float64) / FLIGHT_RATE_HZ
        stream.pending = {k: np.asarray(v, dtype=np.float64) for k, v in channels.items()}
        stream.pending_pos = 0

    def next_batch(
        self, stream: _Stream, n_samples: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        return _take(stream, n_samples, FLIGHT_RATE_HZ, lambda: self._next_chunk(stream))


#: Friction drives: the plant at 1 kHz (the prognosis tuning of the estimator assumes it),
#: simulated in chunks that carry the contact quality and speeds over.
DRIVE_KIND = "friction_drive"
DRIVE_RATE_HZ = 1000.0
DRIVE_CHUNK_S = 10.0
#: Wear rates of the demo drives, one per aircraft in turn: failure (Dn = 0.9) after about
#: 220 s at m = 0.01 under the 20 A square wave, ten times later at 0.001.
DRIVE_WEAR_RATES = (0.001, 0.01, 0.003)
#: RUL levels for the demo drives (stream seconds), scaled to their short lives.
DRIVE_ESTIMATORS = {
    "deterioration_ekf": {
        "sample_period_s": 1.0 / DRIVE_RATE_HZ,
        "rul_watch_s": 600.0,
        "rul_alert_s": 120.0,
    }
}


class _Drives:
    """Friction-drive telemetry: the plant wears continuously across chunks."""

    def __init__(self) -> None:
        self.plant: dict[int, tuple[float, float, float]] = {}  # id(stream) -> alpha, w1, w2

    def _next_chunk(self, stream: _Stream) -> None:
        from estimators.simulators.friction_drive import simulate_friction_drive

        alpha, w1, w2 = self.plant.get(id(stream), (10.0, 0.0, 0.0))
        # One sample more than the chunk: its true state starts the next chunk, so that the plant
        # runs on without a repeated or skipped step.
        t, channels, truth = simulate_friction_drive(
            DRIVE_CHUNK_S + 1.0 / DRIVE_RATE_HZ,
            DRIVE_RATE_HZ,
            alpha0=alpha,
            m=stream.wear_rate,
            seed=stream.seed * 1_000_003 + stream.cycle_index,
            initial_speeds=(w1, w2),
            t0_s=stream.cycle_index * DRIVE_CHUNK_S,
        )
        self.plant[id(stream)] = (
            float(truth["alpha"][-1]),
            float(truth["w1"][-1]),
            float(truth["w2"][-1]),
        )
        stream.cycle_index += 1
        n = len(t) - 1
        stream.pending_t = stream.t_next_s + np.arange(n, dtype=np.float64) / DRIVE_RATE_HZ
        stream.pending = {k: np.asarray(v[:n], dtype=np.float64) for k, v in channels.items()}
        stream.pending_pos = 0

    def next_batch(
        self, stream: _Stream, n_samples: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        return _take(stream, n_samples, DRIVE_RATE_HZ, lambda: self._next_chunk(stream))


def _take(
    stream: _Stream, n_samples: int, rate_hz: float, refill: Callable[[], None]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The next ``n_samples`` of a chunked stream, refilling its pending chunk as needed."""
    t_parts: list[np.ndarray] = []
    parts: dict[str, list[np.ndarray]] = {}
    needed = n_samples
    while needed > 0:
        if stream.pending_t is None or stream.pending_pos >= len(stream.pending_t):
            refill()
        assert stream.pending_t is not None and stream.pending is not None
        take = min(needed, len(stream.pending_t) - stream.pending_pos)
        sl = slice(stream.pending_pos, stream.pending_pos + take)
        t_parts.append(stream.pending_t[sl])
        for name, values in stream.pending.items():
            parts.setdefault(name, []).append(values[sl])
        stream.pending_pos += take
        needed -= take
        # The next chunk (refilled on the next turn) starts one period after this part.
        stream.t_next_s = float(t_parts[-1][-1]) + 1.0 / rate_hz
    t_s = np.concatenate(t_parts)
    return t_s, {name: np.concatenate(chunks) for name, chunks in parts.items()}


def demo_layout(
    aircraft: int, actuators_per_aircraft: int, seed: int, tail_prefix: str = "FH"
) -> Iterator[tuple[str, str, float, float | None]]:
    """(tail, actuator id, load in lbs, degradation pace) of each demo actuator.

    Loads spread over the FLEA range (-45 to +45 lbs). The pace is None for a healthy actuator,
    else a factor on ``degrade_over_s``: the last actuator of every second aircraft degrades at
    pace 1 and the first actuator of the last aircraft at pace 2 (twice as slowly), so that a
    fleet of three shows a healthy aircraft, one in alert and one passing through watch.
    """
    rng = np.random.default_rng(seed)
    for a in range(aircraft):
        tail = f"{tail_prefix}-{a + 1:03d}"
        for k in range(actuators_per_aircraft):
            actuator_id = ACTUATOR_NAMES[k] if k < len(ACTUATOR_NAMES) else f"ema-{k + 1}"
            load_lbs = float(np.round(rng.uniform(-45.0, 45.0), 1))
            pace: float | None = None
            if a % 2 == 1 and k == actuators_per_aircraft - 1:
                pace = 1.0
            elif aircraft > 1 and a == aircraft - 1 and k == 0:
                pace = 2.0
            yield tail, actuator_id, load_lbs, pace


TRANSPORTS = ("rest", "ws")
#: Limit on one call into the WebSocket event loop (open, send), seconds.
WS_CALL_TIMEOUT_S = 120.0
#: Limit on waiting for every frame of a stream to be logged and applied at the end, seconds.
WS_DRAIN_TIMEOUT_S = 60.0
#: Limit on joining the event-loop thread at the end, seconds.
WS_THREAD_JOIN_S = 10.0
T = TypeVar("T")


class _WsSenders:
    """One WebSocket stream per actuator, driven from the simulator's synchronous loop through an
    event loop in a background thread."""

    def __init__(self, base_url: str, api_key: str, binary: bool) -> None:
        self.base_url = base_url
        self.api_key = api_key
        self.binary = binary
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(
            target=self.loop.run_forever, name="simulate-ws", daemon=True
        )
        self.thread.start()
        self.streams: dict[tuple[str, str], FrameStreamer] = {}

    def _run(self, coro: Coroutine[Any, Any, T], timeout_s: float = WS_CALL_TIMEOUT_S) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def send(
        self, tail: str, actuator_id: str, t_s: np.ndarray, channels: dict[str, np.ndarray]
    ) -> None:
        key = (tail, actuator_id)
        if key not in self.streams:
            fs = FrameStreamer(self.base_url, self.api_key, tail, actuator_id, binary=self.binary)
            self._run(fs.open())
            self.streams[key] = fs
        self._run(self.streams[key].send(channels, t_s=t_s))

    def close(self) -> None:
        for fs in self.streams.values():
            try:
                self._run(fs.drain(WS_DRAIN_TIMEOUT_S))
            finally:
                self._run(fs.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(WS_THREAD_JOIN_S)
        self.loop.close()


def run_simulation(
    base_url: str,
    api_key: str,
    *,
    aircraft: int = 3,
    actuators_per_aircraft: int = 2,
    sample_rate_hz: float = 100.0,
    batch_seconds: float = 1.0,
    duration_s: float | None = None,
    realtime: bool = True,
    fmt: str = "arrow",
    seed: int = 0,
    tail_prefix: str = "FH",
    degrade_over_s: float | None = None,
    ready_timeout_s: float | None = None,
    stop_event: threading.Event | None = None,
    log: Log = print,
    transport: str = "rest",
    flight_controls: bool = False,
    faults: str = "random",
    friction_drives: bool = False,
) -> SimulationSummary:
    """Register a demo fleet and stream simulated EMA telemetry to it.

    Args:
        base_url: server address, e.g. ``"http://127.0.0.1:8000"``.
        api_key: key with the ``ingest`` and ``read`` scopes (``admin`` to register aircraft).
        aircraft: number of aircraft.
        actuators_per_aircraft: EMA actuators on each tail.
        sample_rate_hz: plant sampling rate.
        batch_seconds: stream time in one batch.
        duration_s: stream time to send per actuator; ``None`` runs until ``stop_event`` is set.
        realtime: pace batches on the wall clock; False sends as fast as the server takes them.
        fmt: telemetry encoding, ``"arrow"``, ``"json"`` or ``"csv"``.
        seed: seed of loads and plant noise.
        tail_prefix: tails are ``<prefix>-001``, ``<prefix>-002``, ...
        degrade_over_s: stream seconds over which the fastest degrading actuator goes from
            healthy to full friction; default 300 s in real time, else ``duration_s`` (or 300 s).
        ready_timeout_s: how long to wait for the server to accept telemetry; None waits
            however long it takes (a progress line every few seconds). Batches are sent as soon
            as it does; while kernels still compile, progress lines follow.
        stop_event: set it to stop after the current batch.
        log: receives one line per notable event.
        flight_controls: also give every aircraft a ``flight-controls`` unit (kind
            ``flight_controls``, STMMAE attached) flying the reference UAV at 100 Hz.
        faults: surface faults injected into the flight controls of every second aircraft:
            ``"random"`` (a stuck and an oscillating surface per 300 s flight), ``"paper"`` (the
            seed paper's five-fault sequence) or ``"none"``.
        friction_drives: also give every aircraft a ``taxi-drive`` (kind ``friction_drive``,
            deterioration EKF with RUL) that wears under a 20 A square-wave current at 1 kHz,
            with wear rates from :data:`DRIVE_WEAR_RATES`.
        transport: ``"rest"`` posts batches; ``"ws"`` streams them as WebSocket frames (JSON
            frames for ``fmt="json"``, Arrow frames otherwise), resuming after a dropped
            connection.

    Returns:
        counts of what was sent.
    """
    if fmt not in BATCH_FORMATS:
        raise ValueError(f"unknown format {fmt!r}")
    if faults not in FAULT_MODES:
        raise ValueError(f"unknown fault mode {faults!r}; use one of {', '.join(FAULT_MODES)}")
    if transport not in TRANSPORTS:
        raise ValueError(f"unknown transport {transport!r}; use one of {', '.join(TRANSPORTS)}")
    if sample_rate_hz <= 0 or batch_seconds <= 0:
        raise ValueError("sample_rate_hz and batch_seconds must be positive")
    if duration_s is None and stop_event is None:
        raise ValueError("give duration_s or a stop_event, or the simulation never ends")
    if degrade_over_s is None:
        degrade_over_s = 300.0 if realtime or duration_s is None else duration_s
    samples_per_batch = max(1, round(batch_seconds * sample_rate_hz))
    summary = SimulationSummary()
    simulate = _load_simulator()

    with FleetHealthClient(base_url, api_key, timeout=30.0) as client:
        ready = wait_for_server(
            client, timeout_s=ready_timeout_s, stop_event=stop_event, log=log, prefix="simulate: "
        )
        if ready is None:
            if stop_event is None or not stop_event.is_set():
                log(f"simulate: server at {base_url} not ready, giving up")
                summary.errors += 1
            return summary
        kinds = {"fakf"}
        if flight_controls:
            kinds.add("stmmae")
        if friction_drives:
            kinds.add("deterioration_ekf")
        progress = KernelProgress(client, kinds, log=log, prefix="simulate: ")

        now_s = time.time()
        streams: list[_Stream] = []
        for index, (tail, actuator_id, load_lbs, pace) in enumerate(
            demo_layout(aircraft, actuators_per_aircraft, seed, tail_prefix)
        ):
            if tail not in summary.aircraft:
                client.create_aircraft(tail, description="simulated EMA demo aircraft")
                summary.aircraft.append(tail)
            client.create_actuator(tail, actuator_id, kind=ACTUATOR_KIND, channels=list(CHANNELS))
            t_last = client.health(tail, actuator_id).get("t_last_s")
            t_start = now_s if t_last is None else max(now_s, float(t_last) + 1.0 / sample_rate_hz)
            if not realtime and t_last is not None:
                t_start = float(t_last) + 1.0 / sample_rate_hz
            streams.append(
                _Stream(
                    tail=tail,
                    actuator_id=actuator_id,
                    load_lbs=load_lbs,
                    degrade_over_s=None if pace is None else pace * degrade_over_s,
                    seed=seed * 10_007 + index,
                    t_next_s=t_start,
                    t_begin_s=t_start,
                )
            )
            summary.actuators.append((tail, actuator_id))
            wear = "" if pace is None else f", friction grows over {pace * degrade_over_s:g} s"
            log(f"simulate: {tail}/{actuator_id} load {load_lbs:+.1f} lbs{wear}")
        if flight_controls:
            for a, tail in enumerate(list(summary.aircraft)):
                actuator_id = "flight-controls"
                client.create_actuator(tail, actuator_id, kind=FLIGHT_KIND)
                t_last = client.health(tail, actuator_id).get("t_last_s")
                t_start = now_s if t_last is None else float(t_last) + 1.0 / FLIGHT_RATE_HZ
                if realtime and t_last is not None:
                    t_start = max(now_s, t_start)
                inject = faults != "none" and a % 2 == 1
                streams.append(
                    _Stream(
                        tail=tail,
                        actuator_id=actuator_id,
                        load_lbs=0.0,
                        degrade_over_s=None,
                        seed=seed * 10_007 + 5_000 + a,
                        t_next_s=t_start,
                        t_begin_s=t_start,
                        kind=FLIGHT_KIND,
                        inject_faults=inject,
                    )
                )
                summary.actuators.append((tail, actuator_id))
                log(
                    f"simulate: {tail}/{actuator_id} flight controls"
                    + (f", {faults} faults" if inject else "")
                )

        if friction_drives:
            for a, tail in enumerate(list(summary.aircraft)):
                actuator_id = "taxi-drive"
                client.create_actuator(
                    tail, actuator_id, kind=DRIVE_KIND, estimators=DRIVE_ESTIMATORS
                )
                t_last = client.health(tail, actuator_id).get("t_last_s")
                if t_last is not None:
                    # The plant's wear is not stored: a drive with data is not resumed.
                    log(f"simulate: {tail}/{actuator_id} has data already; not simulated again")
                    continue
                wear_rate = DRIVE_WEAR_RATES[a % len(DRIVE_WEAR_RATES)]
                streams.append(
                    _Stream(
                        tail=tail,
                        actuator_id=actuator_id,
                        load_lbs=0.0,
                        degrade_over_s=None,
                        seed=seed * 10_007 + 9_000 + a,
                        t_next_s=now_s,
                        t_begin_s=now_s,
                        kind=DRIVE_KIND,
                        wear_rate=wear_rate,
                    )
                )
                summary.actuators.append((tail, actuator_id))
                log(f"simulate: {tail}/{actuator_id} friction drive, wear rate m = {wear_rate:g}")

        def faults_for(stream: _Stream, chunk: int) -> tuple[Any, ...]:
            if not stream.inject_faults:
                return ()
            if faults == "paper":
                from estimators.simulators.uav_closed_loop import PAPER_FAULT_SCHEDULE

                return PAPER_FAULT_SCHEDULE
            return random_fault_schedule(
                np.random.default_rng((stream.seed, chunk)), FLIGHT_CHUNK_S
            )

        flights = _Flights(faults_for)
        flight_batch = max(1, round(batch_seconds * FLIGHT_RATE_HZ))
        drives = _Drives()
        drive_batch = max(1, round(batch_seconds * DRIVE_RATE_HZ))

        fleet = _Fleet(streams, sample_rate_hz, simulate, _nominal_friction())
        ws = _WsSenders(base_url, api_key, binary=fmt != "json") if transport == "ws" else None

        n_batches = None if duration_s is None else math.ceil(duration_s / batch_seconds)
        wall_start = time.monotonic()
        batch_index = 0
        while n_batches is None or batch_index < n_batches:
            if stop_event is not None and stop_event.is_set():
                break
            if realtime:
                # Send a batch once its last sample lies in the past, as a data link would.
                ahead_s = wall_start + (batch_index + 1) * batch_seconds - time.monotonic()
                if ahead_s > 0:
                    if stop_event is not None:
                        if stop_event.wait(ahead_s):
                            break
                    else:
                        time.sleep(ahead_s)
            for stream in streams:
                if stream.kind == FLIGHT_KIND:
                    t_s, channels = flights.next_batch(stream, flight_batch)
                elif stream.kind == DRIVE_KIND:
                    t_s, channels = drives.next_batch(stream, drive_batch)
                else:
                    t_s, channels = fleet.next_batch(stream, samples_per_batch)
                # The batch id is derived from the stream time: unique per stream, stable across
                # retries, and never reused after a restart (time only moves forward).
                batch_id = f"sim-{int(round(t_s[0] * 1000.0))}"
                try:
                    if ws is not None:
                        ws.send(stream.tail, stream.actuator_id, t_s, channels)
                    else:
                        client.post_batch(
                            stream.tail, stream.actuator_id, batch_id, channels, t_s=t_s, fmt=fmt
                        )
                except (ApiError, httpx.TransportError, ConnectionError, StreamRefused) as exc:
                    # Retries are spent: report, leave a gap in this stream, keep the others going.
                    summary.errors += 1
                    log(f"simulate: {stream.tail}/{stream.actuator_id} {batch_id}: {exc!r}")
                    continue
                summary.batches_sent += 1
                summary.samples_sent += len(t_s)
            batch_index += 1
            progress.check()
            summary.stream_seconds = batch_index * samples_per_batch / sample_rate_hz
            if batch_index % max(1, round(60.0 / batch_seconds)) == 0:
                log(
                    f"simulate: {summary.stream_seconds:.0f} s streamed, "
                    f"{summary.batches_sent} batches, {summary.errors} errors"
                )
        if ws is not None:
            ws.close()  # waits until every frame is logged and applied
    log(
        f"simulate: done, {summary.batches_sent} batches, {summary.samples_sent} samples, "
        f"{summary.errors} errors"
    )
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``fleethealth simulate``."""
    parser.description = (
        "Register demo aircraft (FH-001, ...) with EMA actuators and stream simulated current and "
        "voltage to a running server. Some actuators degrade (growing friction) so that the fleet "
        "board shows watch and alert states after a while."
    )
    parser.add_argument(
        "--url",
        default=os.environ.get("FLEETHEALTH_URL", DEFAULT_URL),
        help=f"server address (env FLEETHEALTH_URL; default {DEFAULT_URL})",
    )
    parser.add_argument(
        "--api-key",
        default=os.environ.get("FLEETHEALTH_API_KEY"),
        help="API key with admin, ingest and read scopes (env FLEETHEALTH_API_KEY)",
    )
    parser.add_argument("--aircraft", type=int, default=3, help="number of aircraft (default 3)")
    parser.add_argument(
        "--actuators-per-aircraft", type=int, default=2, help="EMA actuators per aircraft (2)"
    )
    parser.add_argument("--sample-rate-hz", type=float, default=100.0, help="default 100")
    parser.add_argument(
        "--batch-seconds", type=float, default=1.0, help="stream seconds per batch (1)"
    )
    parser.add_argument(
        "--duration-s",
        type=float,
        default=None,
        help="stream seconds to send per actuator (default: until interrupted)",
    )
    parser.add_argument(
        "--fast",
        action="store_true",
        help="send as fast as the server accepts instead of pacing on the wall clock",
    )
    parser.add_argument(
        "--degrade-over-s",
        type=float,
        default=None,
        help="stream seconds for the fastest degrading actuator to reach full friction "
        "(default 300 in real time, else --duration-s)",
    )
    parser.add_argument("--format", choices=BATCH_FORMATS, default="arrow", dest="fmt")
    parser.add_argument(
        "--transport",
        choices=TRANSPORTS,
        default="rest",
        help="rest: POST batches; ws: stream WebSocket frames (Arrow, or JSON with --format json)",
    )
    parser.add_argument(
        "--flight-controls",
        action="store_true",
        help="also fly a flight-controls unit (STMMAE) on every aircraft",
    )
    parser.add_argument(
        "--faults",
        choices=FAULT_MODES,
        default="random",
        help="surface faults injected into every second aircraft's flight controls (random)",
    )
    parser.add_argument(
        "--friction-drives",
        action="store_true",
        help="also run a wearing friction drive (deterioration EKF, RUL) on every aircraft",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--stop-on-stdin-eof",
        action="store_true",
        help="stop when standard input closes (for a process that runs the simulator as its "
        "child, as `fleethealth serve --demo` does)",
    )
    parser.add_argument(
        "--ready-timeout-s",
        type=float,
        default=None,
        help="give up if the server does not accept telemetry within this time "
        "(default: wait however long it takes, with a progress line)",
    )
    parser.add_argument(
        "--tail-prefix", default="FH", help="tails are PREFIX-001, PREFIX-002, ... (default FH)"
    )


#: After standard input closes, seconds left to stop after the current batch before exiting.
STDIN_EOF_GRACE_S = 2.0


def _stop_on_stdin_eof(stop_event: threading.Event) -> None:
    """Stop once standard input closes (raw reads: no buffered reader's lock): after the
    current batch, or at once if that batch takes longer than :data:`STDIN_EOF_GRACE_S`."""
    with contextlib.suppress(OSError):
        while os.read(0, 4096):
            pass
    stop_event.set()
    time.sleep(STDIN_EOF_GRACE_S)
    os._exit(0)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``fleethealth simulate``; returns the process exit code."""
    if not args.api_key:
        print("simulate: give --api-key or set FLEETHEALTH_API_KEY")
        return 2
    stop_event = threading.Event()
    if args.stop_on_stdin_eof:
        threading.Thread(target=_stop_on_stdin_eof, args=(stop_event,), daemon=True).start()
    try:
        summary = run_simulation(
            args.url,
            args.api_key,
            aircraft=args.aircraft,
            actuators_per_aircraft=args.actuators_per_aircraft,
            sample_rate_hz=args.sample_rate_hz,
            batch_seconds=args.batch_seconds,
            duration_s=args.duration_s,
            realtime=not args.fast,
            fmt=args.fmt,
            seed=args.seed,
            tail_prefix=args.tail_prefix,
            degrade_over_s=args.degrade_over_s,
            stop_event=stop_event,
            transport=args.transport,
            flight_controls=args.flight_controls,
            faults=args.faults,
            friction_drives=args.friction_drives,
            ready_timeout_s=args.ready_timeout_s,
        )
    except KeyboardInterrupt:
        stop_event.set()
        print("simulate: interrupted")
        return 130
    except ApiError as exc:
        print(f"simulate: {exc}")
        return 1
    return 0 if summary.errors == 0 else 1
