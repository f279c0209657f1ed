"""Webhooks on SQLite and PostgreSQL with a receiver on 127.0.0.1: allowed targets, signed
deliveries of logged events, retries after a receiver outage, the delivery log, test-fire,
and nothing sent outside the allowed targets."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.webhooks import service
from tests.app.conftest import Api, make_settings
from tests.receiver import Receiver, verify

FAST = {
    "webhook_poll_s": 0.1,
    "webhook_retry_base_s": 0.2,
    "webhook_retry_max_s": 1.0,
    "webhook_timeout_s": 5.0,
}


@pytest.fixture
def hooks(db_url: str) -> Iterator[Api]:
    with TestClient(create_app(make_settings(db_url, **FAST, webhook_max_attempts=4))) as client:
        yield Api(client)


def _allow(api: Api, prefix: str) -> None:
    with api.app.state.db.write() as s:  # type: ignore[attr-defined]
        service.allow_target(s, "default", prefix)


def _subscribe(api: Api, url: str, **body: Any) -> dict[str, Any]:
    r = api.post("/v1/webhooks", json={"url": url, **body})
    assert r.status_code == 201, r.text
    return r.json()  # type: ignore[no-any-return]


def _flip(api: Api, tail: str = "N1", act: str = "ema1") -> None:
    """A batch that turns the actuator's status unknown: one status_changed, one alarm_raised."""
    api.setup_actuator(tail, act)
    n = 800
    r = api.send_json(tail, act, "flat", np.arange(n) * 0.001, {"current": np.ones(n), "voltage": np.ones(n)})
    assert r.status_code == 202, r.text


def _deliveries(api: Api, sub_id: int, want: int, status: str = "delivered", timeout_s: float = 60) -> list[dict[str, Any]]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        items = api.get(f"/v1/webhooks/{sub_id}/deliveries").json()["items"]
        if sum(d["status"] == status for d in items) >= want:
            return items  # type: ignore[no-any-return]
        time.sleep(0.05)
    raise AssertionError(f"not {want} {status} deliveries in {timeout_s} s: {items}")


def test_only_urls_within_the_allowed_targets_are_accepted(hooks: Api) -> None:
    assert hooks.post("/v1/webhooks", json={"url": "http://127.0.0.1:9/x"}).status_code == 422  # none allowed
    _allow(hooks, "http://127.0.0.1:9/hooks")
    assert hooks.get("/v1/webhooks/targets").json() == {"prefixes": ["http://127.0.0.1:9/hooks"]}
    for bad in (
        "http://127.0.0.1:9/hooksmith",  # not below the prefix at a '/' boundary
        "http://127.0.0.1:10/hooks",  # other port
        "https://127.0.0.1:9/hooks",  # other scheme
        "http://127.0.0.1.evil.example:9/hooks",  # other host
        "http://user:pw@127.0.0.1:9/hooks",  # credentials
        "ftp://127.0.0.1:9/hooks",
    ):
        r = hooks.post("/v1/webhooks", json={"url": bad})
        assert r.status_code == 422, (bad, r.text)
    sub = _subscribe(hooks, "http://127.0.0.1:9/hooks/fleet", event_types=["alarm_raised"])
    assert sub["secret"].startswith("whsec_") and sub["event_types"] == ["alarm_raised"]
    assert "secret" not in hooks.get(f"/v1/webhooks/{sub['id']}").json()
    assert hooks.post("/v1/webhooks", json={"url": "http://127.0.0.1:9/hooks", "event_types": ["x"]}).status_code == 422
    assert hooks.c.delete(f"/v1/webhooks/{sub['id']}", headers=hooks.h).status_code == 204
    assert hooks.get(f"/v1/webhooks/{sub['id']}").status_code == 404


def test_events_are_delivered_signed_with_an_idempotency_key(hooks: Api) -> None:
    with Receiver() as rx:
        _allow(hooks, rx.url)
        sub = _subscribe(hooks, f"{rx.url}/in", secret="s3cret-for-the-test-only")
        _flip(hooks)
        got = rx.wait_for(2)
        events = [r.json["event"] for r in got]
        assert sorted(e["type"] for e in events) == ["alarm_raised", "status_changed"]
        for r in got:
            assert r.path == "/in"
            assert verify("s3cret-for-the-test-only", r.headers, r.body)
            assert not verify("another-secret-entirely", r.headers, r.body)
            assert not verify("s3cret-for-the-test-only", r.headers, r.body + b" ")  # body altered
            # A replay long after the fact is refused by its timestamp.
            assert not verify("s3cret-for-the-test-only", r.headers, r.body, now=time.time() + 3600)
            assert r.json["subscription_id"] == sub["id"]
            assert r.headers["idempotency-key"] == f"fh-1-{r.json['event']['id']}-{sub['id']}"
            assert r.headers["x-fleethealth-event"] == r.json["event"]["type"]
        log = _deliveries(hooks, sub["id"], 2)
        assert all(d["attempts"] == 1 and d["log"][0]["status_code"] == 200 for d in log)


def test_a_receiver_outage_is_retried_with_back_off_and_the_same_key(hooks: Api) -> None:
    with Receiver(fail_first=2) as rx:
        _allow(hooks, rx.url)
        sub = _subscribe(hooks, rx.url + "/", event_types=["status_changed"])
        _flip(hooks)
        (ok,) = rx.wait_for(1)
        tries = rx.received
        assert [r.status for r in tries] == [503, 503, 200]
        assert len({r.headers["idempotency-key"] for r in tries}) == 1
        assert [r.headers["x-fleethealth-attempt"] for r in tries] == ["1", "2", "3"]
        assert len({r.body for r in tries}) == 1  # the same bytes every time
        (d,) = _deliveries(hooks, sub["id"], 1)
        assert d["attempts"] == 3 and [a["status_code"] for a in d["log"]] == [503, 503, 200]
        assert d["log"][0]["error"] == "HTTP 503"


def test_a_delivery_gives_up_after_its_last_attempt(hooks: Api) -> None:
    with Receiver() as rx:
        rx.down = True
        _allow(hooks, rx.url)
        sub = _subscribe(hooks, rx.url, event_types=["status_changed"])
        _flip(hooks)
        (d,) = _deliveries(hooks, sub["id"], 1, status="failed")
        assert d["attempts"] == 4 and len(rx.received) == 4
        assert hooks.get(f"/v1/webhooks/{sub['id']}/deliveries?status=pending").json()["items"] == []


def test_test_fire_and_no_delivery_after_the_target_is_withdrawn(hooks: Api) -> None:
    with Receiver() as rx:
        _allow(hooks, rx.url)
        sub = _subscribe(hooks, rx.url)
        r = hooks.post(f"/v1/webhooks/{sub['id']}/test")
        assert r.status_code == 202, r.text
        (got,) = rx.wait_for(1)
        assert got.json["event"]["type"] == "webhook_test" and got.headers["x-fleethealth-event"] == "webhook_test"
        with hooks.app.state.db.write() as s:  # type: ignore[attr-defined]
            assert service.disallow_target(s, "default", rx.url)
        _flip(hooks)
        log = _deliveries(hooks, sub["id"], 2, status="failed")
        assert all("allowed" in (d["last_error"] or "") for d in log if d["status"] == "failed")
        assert len(rx.received) == 1  # nothing sent after the withdrawal
    assert hooks.post("/v1/webhooks/999/test").status_code == 404


def test_url_matching_rules() -> None:
    assert service.url_allowed("https://h.example/a/b?x=1", ["https://h.example/a"])
    assert service.url_allowed("https://H.example:443/a", ["https://h.example/a/"]) is False  # /a is not below /a/
    assert service.url_allowed("https://h.example:443/a/b", ["https://h.example/a/"])
    assert not service.url_allowed("https://h.example/ab", ["https://h.example/a"])
    assert not service.url_allowed("https://h.example@evil.example/a", ["https://h.example/a"])
    assert not service.url_allowed("not a url", ["https://h.example/"])
    assert service.backoff_s(1, 5, 60) == 5 and service.backoff_s(3, 5, 60) == 20 and service.backoff_s(9, 5, 60) == 60


@pytest.mark.postgres
def test_two_deliverers_on_postgresql_never_send_a_delivery_twice(db_url: str) -> None:
    import threading

    from app.webhooks.deliverer import Deliverer

    if not db_url.startswith("postgresql"):
        pytest.skip("several deliverers share a database on PostgreSQL only")
    # No deliverer thread of the app's own: the two below race each other.
    settings = make_settings(db_url, **FAST, webhooks_enabled=False, webhook_batch=8)
    with TestClient(create_app(settings)) as client, Receiver(delay_s=0.2) as rx:
        api = Api(client)
        _allow(api, rx.url)
        sub = _subscribe(api, rx.url)
        n = 24
        for _ in range(n):
            assert api.post(f"/v1/webhooks/{sub['id']}/test").status_code == 202
        db = api.app.state.db  # type: ignore[attr-defined]
        deliverers = [Deliverer(db, settings) for _ in range(2)]
        sent = [0, 0]
        start = threading.Barrier(2)

        def work(i: int) -> None:
            start.wait()
            for _ in range(20):  # bounded rounds
                sent[i] += deliverers[i].deliver_due()

        threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        for d in deliverers:
            d.stop()
        keys = [r.headers["idempotency-key"] for r in rx.received]
        assert len(keys) == n and len(set(keys)) == n  # every delivery sent, none twice
        assert sum(sent) == n and min(sent) > 0  # both took part: locked rows were skipped
        assert len(_deliveries(api, sub["id"], n)) == n
