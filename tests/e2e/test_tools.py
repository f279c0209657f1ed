"""``fleethealth replay`` and ``simulate`` against a real server process on 127.0.0.1."""

from __future__ import annotations

import contextlib
import math
import os
import secrets
import shlex
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from fleethealth_client import FleetHealthClient
from scipy.signal import lfilter

from estimators.flea import flea_dir
from fleethealth_tools.replay import flea_actuator_id

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[2]
FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")
FLEA_RUN = "BatchProfile_sine11_2010_09_03_09_51_40_Nominal_Low.data.gz"
COMPOSE_COMMAND = "fleethealth migrate && fleethealth serve --host 0.0.0.0 --port 8000"


# ------------------------------------------------------------------------------------------------
# Servers: the shared ``live_server`` (tests/e2e/conftest.py), and the compose file's own command
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Server:
    url: str
    api_key: str


@pytest.fixture
def server(live_server: Any) -> _Server:
    return _Server(live_server.url, live_server.api_key)


@pytest.fixture
def client(server: _Server) -> Iterator[FleetHealthClient]:
    with FleetHealthClient(server.url, server.api_key, timeout=60.0) as c:
        yield c


def _compose_app() -> dict[str, Any]:
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    return compose["services"]["app"]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def compose_server(tmp_path: Path) -> Iterator[_Server]:
    """The app service's command from docker/compose.yaml, run as written except for the
    address (127.0.0.1 and a free port) and the database (a temporary SQLite file)."""
    import httpx

    command = _compose_app()["command"]
    assert command[:2] == ["sh", "-c"] and command[2] == COMPOSE_COMMAND
    port = _free_port()
    shell_command = command[2].replace(
        "--host 0.0.0.0 --port 8000", f"--host 127.0.0.1 --port {port}"
    )
    api_key = secrets.token_urlsafe(24)
    env = dict(os.environ)
    env["PATH"] = f"{Path(FLEETHEALTH).parent}{os.pathsep}{env.get('PATH', '')}"
    env["FLEETHEALTH_DATABASE_URL"] = f"sqlite:///{tmp_path / 'compose.db'}"
    env["FLEETHEALTH_BOOTSTRAP_ADMIN_KEY"] = api_key
    log_path = tmp_path / "server.log"
    with open(log_path, "wb") as log:
        # A session of its own, so that the shell and the server it starts stop together.
        process = subprocess.Popen(
            ["sh", "-c", shell_command],
            env=env,
            cwd=tmp_path,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180.0
        while True:
            if process.poll() is not None:
                pytest.fail(f"server exited:\n{log_path.read_text(errors='replace')[-3000:]}")
            with contextlib.suppress(httpx.TransportError):  # not listening yet
                if httpx.get(url + "/readyz", timeout=2.0).status_code == 200:
                    break
            if time.monotonic() > deadline:
                pytest.fail(f"server not ready:\n{log_path.read_text(errors='replace')[-3000:]}")
            time.sleep(0.2)
        assert httpx.get(url + "/healthz", timeout=5.0).status_code == 200
        yield _Server(url, api_key)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(timeout=10)


@pytest.fixture
def compose_client(compose_server: _Server) -> Iterator[FleetHealthClient]:
    with FleetHealthClient(compose_server.url, compose_server.api_key, timeout=60.0) as c:
        yield c


def _cli_env(server: _Server) -> dict[str, str]:
    env = dict(os.environ)
    env["FLEETHEALTH_API_KEY"] = server.api_key
    return env


def _fleet_actuators(client: FleetHealthClient, tail: str) -> dict[str, dict]:
    for aircraft in client.fleet_health(sort="tail")["aircraft"]:
        if aircraft["tail"] == tail:
            return {a["actuator_id"]: a for a in aircraft["actuators"]}
    return {}


def _assert_fakf_window(health: dict) -> dict:
    fakf = health["estimators"]["fakf"]
    assert fakf["status"] in ("ok", "watch", "alert")
    window = fakf["window"]
    assert window is not None, "no completed FAKF health window"
    assert window["n_samples"] > 0 and window["t_end_s"] > window["t_start_s"]
    indicators = window["indicators"]
    assert indicators, "FAKF window without indicators"
    return indicators


# ------------------------------------------------------------------------------------------------
# Replay
# ------------------------------------------------------------------------------------------------


@pytest.mark.flea
def test_replay_flea_run_gives_fakf_health(request: pytest.FixtureRequest) -> None:
    run_path = flea_dir() / "runs" / FLEA_RUN
    if not run_path.is_file():
        pytest.skip(f"FLEA data not found at {run_path} (set FLEETHEALTH_FLEA_DIR)")
    # Only now start the server: a skipped test should not pay for it.
    server: _Server = request.getfixturevalue("server")
    client: FleetHealthClient = request.getfixturevalue("client")
    tail = "FLEA-E2E"
    command = [
        FLEETHEALTH,
        "replay",
        "--url",
        server.url,
        "--tail",
        tail,
        "--format",
        "csv",
        "--batch-samples",
        "700",
        "--wait",
        str(run_path),
    ]
    done = subprocess.run(
        command, env=_cli_env(server), capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stdout + done.stderr
    actuator_id = flea_actuator_id(run_path.name.removesuffix(".data.gz"))
    assert actuator_id in done.stdout  # --wait prints the health

    health = client.health(tail, actuator_id)
    assert health["last_applied_seq"] == health["last_logged_seq"] == 5  # 2970 samples / 700
    indicators = _assert_fakf_window(health)
    # The seed's claim on FLEA data: the filter beats the model alone.
    assert indicators["mae"] is not None and indicators["model_mae"] is not None
    assert indicators["mae"] < indicators["model_mae"]

    history = client.health_history(tail, actuator_id, estimator="fakf")
    assert len(history) >= 2
    assert all(math.isfinite(item["t_end_s"]) for item in history)
    # Absolute times: the run started on 2010-09-03.
    assert 1283400000 < history[0]["t_start_s"] < 1283600000

    fleet_entry = _fleet_actuators(client, tail)[actuator_id]
    assert fleet_entry["kind"] == "ema_voltage"
    assert fleet_entry["last_applied_seq"] == 5

    # A second replay of the same file re-sends the same batch ids: nothing is applied twice.
    again = subprocess.run(
        command, env=_cli_env(server), capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0, again.stdout + again.stderr
    assert client.health(tail, actuator_id)["last_applied_seq"] == 5


def _arx_csv(path: Path, t0: float, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) / 100.0
    current = np.sin(2 * np.pi * 0.4 * (t - t0)) + 0.3 * np.sin(2 * np.pi * 2.3 * (t - t0))
    current += rng.normal(0.0, 0.05, n)
    voltage = lfilter([-0.7889, 5.9267, -3.5857], [1.0, -0.4998, -0.0343], current)
    voltage += rng.normal(0.0, 0.5, n)
    voltage[rng.choice(n, 20, replace=False)] = np.nan
    lines = ["t,current,voltage"]
    lines += [
        f"{ti!r},{ci!r},{'' if math.isnan(vi) else repr(vi)}"
        for ti, ci, vi in zip(t.tolist(), current.tolist(), voltage.tolist(), strict=True)
    ]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("fmt", ["json", "arrow"])
def test_replay_csv_files_into_one_actuator(
    server: _Server, client: FleetHealthClient, tmp_path: Path, fmt: str
) -> None:
    # Two recordings given newest first: replay sends them in time order into one stream.
    _arx_csv(tmp_path / "later.csv", t0=1_700_000_100.0, n=2500, seed=2)
    _arx_csv(tmp_path / "first.csv", t0=1_700_000_000.0, n=2500, seed=1)
    tail = f"CSV-{fmt.upper()}"
    done = subprocess.run(
        [
            FLEETHEALTH,
            "replay",
            "--url",
            server.url,
            "--tail",
            tail,
            "--actuator",
            "bench-ema",
            "--format",
            fmt,
            "--wait",
            str(tmp_path / "later.csv"),
            str(tmp_path / "first.csv"),
        ],
        env=_cli_env(server),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    health = client.health(tail, "bench-ema")
    assert health["last_applied_seq"] == 6  # 3 batches of at most 1000 samples per file
    assert health["t_last_s"] == pytest.approx(1_700_000_100.0 + 2499 / 100.0)
    indicators = _assert_fakf_window(health)
    assert indicators["mae"] < indicators["model_mae"]
    assert set(_fleet_actuators(client, tail)) == {"bench-ema"}


# ------------------------------------------------------------------------------------------------
# Simulate
# ------------------------------------------------------------------------------------------------


def test_simulate_registers_fleet_and_degradation_shows_in_fakf_health(
    compose_server: _Server, compose_client: FleetHealthClient
) -> None:
    """Against the server started by the compose file's command."""
    from fleethealth_tools.simulate import run_simulation

    server, client = compose_server, compose_client

    lines: list[str] = []
    summary = run_simulation(
        server.url,
        server.api_key,
        aircraft=2,
        actuators_per_aircraft=2,
        sample_rate_hz=100.0,
        batch_seconds=5.0,
        duration_s=120.0,
        degrade_over_s=120.0,
        realtime=False,
        fmt="arrow",
        seed=3,
        tail_prefix="SIM",
        log=lines.append,
        flight_controls=True,
        faults="paper",
        friction_drives=True,
    )
    assert summary.errors == 0, lines
    assert summary.aircraft == ["SIM-001", "SIM-002"]
    assert summary.actuators == [
        ("SIM-001", "ema-left"),
        ("SIM-001", "ema-right"),
        ("SIM-002", "ema-left"),
        ("SIM-002", "ema-right"),
        ("SIM-001", "flight-controls"),
        ("SIM-002", "flight-controls"),
        ("SIM-001", "taxi-drive"),
        ("SIM-002", "taxi-drive"),
    ]
    assert summary.samples_sent == 6 * 12_000 + 2 * 120_000

    # Taxi drives: SIM-002's wears ten times faster (m = 0.01 against 0.001); its RUL is shorter
    # and the board sorted by RUL lists its aircraft first.
    for tail in ("SIM-001", "SIM-002"):
        client.wait_applied(tail, "taxi-drive", seq=24, timeout_s=120.0)
    rul = {t: client.rul(t, "taxi-drive")["latest"]["deterioration_ekf"] for t in ("SIM-001", "SIM-002")}
    assert rul["SIM-002"]["q50_s"] < 0.3 * rul["SIM-001"]["q50_s"]
    assert [a["tail"] for a in client.fleet_health(sort="rul")["aircraft"]][:2] == ["SIM-002", "SIM-001"]

    # Flight controls: SIM-002 flies the seed paper's fault sequence (left aileron stuck from
    # 10 to 40 s, right aileron oscillating from 70 to 100 s), SIM-001 flies without faults.
    for tail in ("SIM-001", "SIM-002"):
        client.wait_applied(tail, "flight-controls", seq=24, timeout_s=120.0)
    # (The false-alarm rate of the bank is the estimator's business, measured in
    # docs/validation.md; here only the injection is checked.)
    faulty = client.faults("SIM-002", "flight-controls")
    detected = [
        (e["detail"]["component"], e["detail"]["detected_s"] - faulty_t0)
        for faulty_t0 in [_first_t(client, "SIM-002", "flight-controls")]
        for e in faulty["events"]
        if e["kind"] == "fault_detected"
    ]
    assert ("aileron_left" in [c for c, t in detected if 10.0 <= t < 40.0]), detected
    assert ("aileron_right" in [c for c, t in detected if 70.0 <= t < 100.0]), detected

    t_last: dict[tuple[str, str], float] = {}
    for tail, actuator_id in summary.actuators[:4]:
        actuator = client.get_actuator(tail, actuator_id)
        assert actuator["kind"] == "ema_voltage"
        assert actuator["channels"] == ["current", "voltage"]
        health = client.wait_applied(tail, actuator_id, seq=24, timeout_s=120.0)
        _assert_fakf_window(health)
        t_last[(tail, actuator_id)] = health["t_last_s"]

    # SIM-001 is healthy; SIM-002's right EMA binds fully within the run (its left one at half
    # pace). The FAKF sees it: innovations grow against the model identified at the start.
    for actuator_id in ("ema-left", "ema-right"):
        assert client.health("SIM-001", actuator_id)["status"] == "ok"
    binding = client.health("SIM-002", "ema-right")
    assert binding["status"] in ("watch", "alert"), binding["estimators"]["fakf"]["reasons"]
    history = client.health_history("SIM-002", "ema-right", estimator="fakf", limit=1000)
    ratios = [item["indicators"]["innovation_rms_ratio"] for item in history]
    assert ratios[-1] > 1.5 * ratios[1]

    fleet = {a["tail"]: a for a in client.fleet_health(sort="status")["aircraft"]}
    assert fleet["SIM-001"]["status"] == "ok"
    assert fleet["SIM-002"]["status"] in ("watch", "alert")
    assert len(fleet["SIM-002"]["actuators"]) == 4  # two EMAs, flight controls, taxi drive

    # A second run, streaming over WebSocket, continues each stream after its last sample
    # instead of colliding with it.
    again = run_simulation(
        server.url,
        server.api_key,
        aircraft=2,
        actuators_per_aircraft=2,
        batch_seconds=5.0,
        duration_s=10.0,
        realtime=False,
        seed=3,
        tail_prefix="SIM",
        log=lines.append,
        transport="ws",
    )
    assert again.errors == 0, lines
    for (tail, actuator_id), t_before in t_last.items():
        health = client.wait_applied(tail, actuator_id, seq=26, timeout_s=120.0)
        assert health["t_last_s"] == pytest.approx(t_before + 10.0)


def _first_t(client: FleetHealthClient, tail: str, actuator_id: str) -> float:
    out = client.outputs(tail, actuator_id, estimator="stmmae")
    return float(out["t_s"][0])


# ------------------------------------------------------------------------------------------------
# Compose file: the commands it runs are the ones these tests run
# ------------------------------------------------------------------------------------------------


def test_compose_runs_the_tested_commands() -> None:
    from app.cli import build_parser

    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    app_service = compose["services"]["app"]
    assert app_service["command"] == ["sh", "-c", COMPOSE_COMMAND]
    assert (
        app_service["environment"]["FLEETHEALTH_DATABASE_URL"]
        == "postgresql+psycopg://fleethealth:fleethealth@db:5432/fleethealth"
    )
    assert "/healthz" in " ".join(app_service["healthcheck"]["test"])
    assert compose["services"]["db"]["image"] == "postgres:15"
    parser = build_parser()
    for part in COMPOSE_COMMAND.split("&&"):
        argv = shlex.split(part)
        assert argv[0] == "fleethealth"
        assert parser.parse_args(argv[1:]).cmd in ("migrate", "serve")
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    assert f'CMD ["sh", "-c", "{COMPOSE_COMMAND}"]' in dockerfile
