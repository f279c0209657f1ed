"""The dashboard in a real browser: Debian's Chromium driven by Playwright against a real server.

One server per module, fed by the simulator. Every wait is for a condition, with generous
bounds (two busy cores; a cold numba cache compiles for minutes before the first apply).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
from fleethealth_client import FleetHealthClient

from fleethealth_tools.showcase import SHA_EMA_ACTUATOR, feed_showcase_fleet
from fleethealth_tools.simulate import run_simulation
from tests.conftest import make_series
from tests.e2e.conftest import LiveServer

playwright_api = pytest.importorskip("playwright.sync_api")

# One test process runs the whole module: its server, fleet and browser are set up once.
pytestmark = [pytest.mark.e2e, pytest.mark.browser, pytest.mark.timeout(1200),
              pytest.mark.xdist_group("dashboard")]

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
WAIT_MS = 240_000  # applying a batch can wait for a cold kernel compile


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    from app.migrate import upgrade

    tmp = tmp_path_factory.mktemp("dashboard")
    url = f"sqlite:///{tmp / 'dash.db'}"
    upgrade(url)
    srv = LiveServer(url, tmp / "server.log")
    srv.start(timeout_s=900.0)
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def read_key(server: LiveServer) -> str:
    """A key with the read scope only: what a dashboard user holds."""
    r = httpx.post(f"{server.url}/v1/keys", headers=server.headers, json={"scopes": ["read"], "name": "dashboard"})
    assert r.status_code == 201, r.text
    return str(r.json()["key"])


@pytest.fixture(scope="module")
def fleet(server: LiveServer) -> dict[str, Any]:
    """The showcase fleet (FH-001, FH-002), every stream applied to its end."""
    feed_showcase_fleet(server.url, server.api_key, duration_s=30.0, log=lambda _line: None)
    with FleetHealthClient(server.url, server.api_key, timeout=60.0) as client:
        board = client.fleet_health()
        for ac in board["aircraft"]:
            for act in ac["actuators"]:
                client.wait_applied(ac["tail"], act["actuator_id"], act["last_logged_seq"], timeout_s=600.0)
        return dict(client.fleet_health())


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install chromium (.ci/run does)")
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser: Any, server: LiveServer) -> Iterator[Any]:
    # The page's CSP forbids eval; the tests' own wait expressions need it.
    context = browser.new_context(viewport={"width": 1400, "height": 1000}, bypass_csp=True)
    pg = context.new_page()
    errors: list[str] = []
    requests: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.on("request", lambda r: requests.append(r.url))
    yield pg
    context.close()
    assert errors == [], f"the page raised: {errors}"
    origin = urlsplit(server.url).netloc
    elsewhere = [u for u in requests if not u.startswith("data:") and urlsplit(u).netloc != origin]
    assert requests and elsewhere == [], f"requests to other hosts: {elsewhere}"


def _open(page: Any, server: LiveServer, key: str, fragment: str = "") -> None:
    page.goto(f"{server.url}/{fragment}")
    page.fill("#key", key)
    page.click("#login button[type=submit]")
    page.wait_for_selector("body[data-ready=true]", timeout=WAIT_MS)


def test_a_wrong_key_is_refused(server: LiveServer, page: Any) -> None:
    page.goto(f"{server.url}/")
    page.fill("#key", "not-a-key-of-this-server")
    page.click("#login button[type=submit]")
    page.wait_for_function("document.getElementById('login-error').textContent.length > 0", timeout=WAIT_MS)
    assert "refused" in page.inner_text("#login-error")
    assert page.is_visible("#login") and page.query_selector("#board") is None
    assert page.evaluate("sessionStorage.getItem('fleethealth.key')") is None
    # A key without the read scope is told so, and not kept either.
    r = httpx.post(f"{server.url}/v1/keys", headers=server.headers, json={"scopes": ["ingest"], "name": "link"})
    page.fill("#key", r.json()["key"])
    page.click("#login button[type=submit]")
    page.wait_for_function("document.getElementById('login-error').textContent.includes('read scope')", timeout=WAIT_MS)
    assert page.evaluate("sessionStorage.getItem('fleethealth.key')") is None


def test_a_fault_injected_by_the_simulator_appears_live(server: LiveServer, read_key: str, page: Any) -> None:
    # The board is open before the fleet exists; it only learns of the fault from the
    # fleet-event stream (the board does not poll), and the page is never reloaded.
    _open(page, server, read_key)
    page.wait_for_selector("#live.on", timeout=WAIT_MS)
    page.evaluate("window.__same_page = true")
    feeder = threading.Thread(
        target=run_simulation,
        args=(server.url, server.api_key),
        kwargs={"aircraft": 2, "actuators_per_aircraft": 1, "duration_s": 30.0, "realtime": False,
                "flight_controls": True, "faults": "paper", "tail_prefix": "LV", "ready_timeout_s": 600.0,
                "log": lambda _line: None},
        daemon=True,
    )
    feeder.start()
    cell = 'tr[data-tail="LV-002"] td[data-actuator="flight-controls"]'
    page.wait_for_selector(f"{cell} [data-fault]", timeout=WAIT_MS * 2)
    assert page.get_attribute(f"{cell} [data-fault]", "data-fault") == "aileron_left"  # the paper's first fault
    page.wait_for_function(  # the status change may arrive a message after the detection
        "(sel) => ['watch', 'alert', 'failed'].includes(document.querySelector(sel).dataset.status)",
        arg=cell, timeout=WAIT_MS,
    )
    assert page.evaluate("window.__same_page") is True
    events = page.inner_text("#events")
    assert "LV-002 / flight-controls: fault_detected aileron_left" in events
    # The aircraft without injected faults shows none.
    assert page.query_selector('tr[data-tail="LV-001"] [data-fault]') is None
    feeder.join(timeout=600)


def test_the_board_lists_the_fleet_and_filters_it(server: LiveServer, read_key: str, fleet: dict[str, Any],
                                                   page: Any) -> None:
    _open(page, server, read_key)
    for ac in fleet["aircraft"]:
        row = f'tr[data-tail="{ac["tail"]}"]'
        page.wait_for_selector(row, timeout=WAIT_MS)
        for act in ac["actuators"]:
            status = page.get_attribute(f'{row} td[data-actuator="{act["actuator_id"]}"]', "data-status")
            assert status in {"learning", "ok", "watch", "alert", "failed", "unknown"}
    assert page.get_attribute(f'tr[data-tail="FH-001"] td[data-actuator="{SHA_EMA_ACTUATOR}"]', "data-status") == "alert"
    tails = {ac["tail"] for ac in fleet["aircraft"]}
    assert {"FH-001", "FH-002"} <= tails
    page.fill("#filter-tail", "FH-002")
    page.wait_for_function("document.querySelectorAll('#board tr[data-tail]').length === 1")
    assert page.get_attribute("#board tr[data-tail]", "data-tail") == "FH-002"
    page.fill("#filter-tail", "")
    page.select_option("#filter-kind", "friction_drive")
    page.wait_for_function("[...document.querySelectorAll('#board td[data-actuator]')].every(td => td.dataset.actuator === 'taxi-drive')")
    assert len(page.query_selector_all("#board td[data-actuator]")) >= 2
    # Sorted by remaining life: the drive that wears fastest (FH-002, m = 0.01) first.
    page.select_option("#sort", "rul")
    page.wait_for_function("document.querySelector('#board tr[data-tail]').dataset.tail === 'FH-002'", timeout=WAIT_MS)


def _chart_data(page: Any, chart: str) -> dict[str, Any]:
    """The data the chart draws: x values and, per series, its finite values."""
    return dict(page.evaluate(
        """(id) => { const c = window.fleethealth.charts[id]; const d = c.u.data;
             return {x: d[0].length, finite: d.slice(1).map(ys => ys.filter(v => v !== null && Number.isFinite(v)).length),
                     x0: d[0][0], x1: d[0][d[0].length - 1], labels: c.u.series.slice(1).map(s => s.label)}; }""",
        chart,
    ))


KIND_CHARTS = {
    "FH-001/ema-left": ["fakf-voltage", "fakf-innovation", "fakf-health"],
    "FH-002/taxi-drive": ["dekf-dn", "dekf-alpha", "dekf-rul", "dekf-rul-dist"],
    "FH-002/flight-controls": ["stmmae-prob", "stmmae-deflection"],
    f"FH-001/{SHA_EMA_ACTUATOR}": ["darr-residuals", "darr-parameters"],
}


@pytest.mark.parametrize("path", list(KIND_CHARTS))
def test_an_actuator_page_draws_its_plots_with_data(server: LiveServer, read_key: str, fleet: dict[str, Any],
                                                    page: Any, path: str) -> None:
    _open(page, server, read_key, f"#/a/{path}")
    for chart in KIND_CHARTS[path]:
        page.wait_for_function("(id) => { const c = window.fleethealth.charts[id]; return c && c.u; }", arg=chart,
                               timeout=WAIT_MS)
        got = _chart_data(page, chart)
        least = 2 if chart == "dekf-rul" else 3  # a prognosis every 10 s of the 30 s fed
        assert got["x"] >= least, (chart, got)
        assert max(got["finite"]) >= least, (chart, got)  # points drawn, not just a canvas


def test_zoom_fetches_finer_data(server: LiveServer, read_key: str, fleet: dict[str, Any], page: Any) -> None:
    _open(page, server, read_key, "#/a/FH-002/taxi-drive")
    page.wait_for_function("() => { const c = window.fleethealth.charts['dekf-dn']; return c && c.u; }", timeout=WAIT_MS)
    before = _chart_data(page, "dekf-dn")
    samples_before = int(page.get_attribute('[data-chart="dekf-dn"]', "data-samples"))
    assert samples_before > before["x"]  # 30 s at 1 kHz, downsampled to the plot's width
    box = page.locator('[data-chart="dekf-dn"] .u-over').bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(box["x"] + box["width"] * 0.40, y)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] * 0.45, y, steps=5)
    page.mouse.up()
    page.wait_for_function(
        "(n) => Number(document.querySelector('[data-chart=\"dekf-dn\"]').dataset.samples) < n",
        arg=samples_before, timeout=WAIT_MS,
    )
    after = _chart_data(page, "dekf-dn")
    assert after["x1"] - after["x0"] < (before["x1"] - before["x0"]) / 5
    # Finer: more samples per second of stream time than the whole-span view had.
    assert after["x"] / (after["x1"] - after["x0"]) > 2 * before["x"] / (before["x1"] - before["x0"])


def test_a_page_without_data_says_so(server: LiveServer, read_key: str, page: Any) -> None:
    with FleetHealthClient(server.url, server.api_key, timeout=60.0) as client:
        client.create_aircraft("NEW-1")
        client.create_actuator("NEW-1", "surface", kind="sha_ema")
    _open(page, server, read_key, "#/a/NEW-1/surface")
    for chart in ("darr-residuals", "darr-parameters"):
        page.wait_for_selector(f'[data-chart="{chart}"] .empty', timeout=WAIT_MS)
        assert page.inner_text(f'[data-chart="{chart}"] .empty') == "no data yet"
    assert "learning" in page.inner_text("#facts")


def test_an_actuator_page_follows_new_telemetry_live(server: LiveServer, read_key: str, page: Any) -> None:
    # The page is open before the actuator has data; it learns of each batch from the fleet-event
    # stream (it does not poll) and is never reloaded.
    fakf = {"fakf": {"identification_samples": 300, "health_window_samples": 250}}
    with FleetHealthClient(server.url, server.api_key, timeout=60.0) as client:
        client.create_aircraft("LIVE-1")
        client.create_actuator("LIVE-1", "ema", kind="ema_voltage", estimators=fakf)
    _open(page, server, read_key, "#/a/LIVE-1/ema")
    page.wait_for_selector("#live.on", timeout=WAIT_MS)
    page.wait_for_selector('[data-chart="fakf-voltage"] .empty', timeout=WAIT_MS)
    assert page.get_attribute("#facts", "data-applied-seq") == "0"
    page.evaluate("window.__same_page = true")
    series = make_series(2000, seed=31)

    def post(batch_id: str, lo: int, hi: int) -> int:
        with FleetHealthClient(server.url, server.api_key, timeout=60.0) as client:
            ack = client.post_batch("LIVE-1", "ema", batch_id, {"current": series.current[lo:hi], "voltage": series.voltage[lo:hi]},
                                    t_s=series.t_s[lo:hi], fmt="arrow")
        return int(ack["seq"])

    assert post("first", 0, 1000) == 1
    page.wait_for_function(
        "() => document.querySelector('#facts').dataset.appliedSeq === '1' && window.fleethealth.charts['fakf-voltage'].u"
        " && window.fleethealth.charts['fakf-health'].u", timeout=WAIT_MS)
    first = _chart_data(page, "fakf-voltage")
    assert first["x"] >= 3 and max(first["finite"]) >= 3
    assert first["x1"] == pytest.approx(series.t_s[999])
    assert post("second", 1000, 2000) == 2
    page.wait_for_function(
        "(t) => document.querySelector('#facts').dataset.appliedSeq === '2'"
        " && window.fleethealth.charts['fakf-voltage'].u.data[0].at(-1) > t", arg=first["x1"], timeout=WAIT_MS)
    second = _chart_data(page, "fakf-voltage")
    assert second["x0"] == pytest.approx(first["x0"]) and second["x1"] == pytest.approx(series.t_s[1999])
    assert "2 / 2" in page.inner_text("#facts")  # applied / logged, read again after the event
    assert page.get_attribute("#facts", "data-status") in {"learning", "ok", "watch", "alert", "unknown"}
    assert page.evaluate("window.__same_page") is True
