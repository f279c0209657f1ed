"""The per-request look-up caches (app/cache.py): an API key is remembered for at most
``auth_cache_ttl_s`` (a key revoked or re-scoped by another process stops working within that
bound), and a remembered actuator never lets a batch into a deleted stream, whichever process
deleted it. Time is a fake clock here: nothing waits, nothing is timed."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.auth.service import create_key, revoke_key, set_scopes
from app.cache import TtlCache
from app.db import Database
from app.fleet import service as fleet
from app.main import create_app
from tests.app.conftest import Api, FakeClock, make_settings

TTL_S = 5.0


def _one_sample(k: int) -> dict[str, object]:
    return {"batch_id": f"b{k}", "t": [float(k)], "channels": {"current": [0.3], "voltage": [-8.0]}}


# ----------------------------------------------------------------------------- the cache itself
def test_entries_expire_after_ttl_and_the_oldest_makes_room() -> None:
    clock = FakeClock()
    cache: TtlCache[str, int] = TtlCache(TTL_S, max_entries=2, clock=clock)
    cache.put("a", 1, cache.generation())
    clock.now += TTL_S - 0.01
    assert cache.get("a") == 1
    clock.now += 0.02
    assert cache.get("a") is None
    for key, value in (("x", 1), ("y", 2), ("z", 3)):
        cache.put(key, value, cache.generation())
    assert len(cache) == 2
    assert cache.get("x") is None
    assert (cache.get("y"), cache.get("z")) == (2, 3)


def test_a_lookup_older_than_an_invalidation_is_not_stored() -> None:
    cache: TtlCache[str, int] = TtlCache(TTL_S, max_entries=10, clock=FakeClock())
    before = cache.generation()  # a look-up reads the database ...
    cache.invalidate("k")  # ... while this process changes the row
    cache.put("k", 1, before)
    assert cache.get("k") is None
    cache.put("k", 2, cache.generation())
    cache.invalidate()
    assert cache.get("k") is None


def test_ttl_zero_remembers_nothing() -> None:
    cache: TtlCache[str, int] = TtlCache(0.0, max_entries=10)
    cache.put("k", 1, cache.generation())
    assert cache.get("k") is None


# ----------------------------------------------------------------------------- API keys
@pytest.fixture
def api_clocked(db_url: str) -> Iterator[tuple[Api, FakeClock]]:
    settings = make_settings(db_url, processor_enabled=False, auth_cache_ttl_s=TTL_S, actuator_cache_ttl_s=3600.0)
    with TestClient(create_app(settings)) as client:
        clock = FakeClock()
        verifier = client.app.state.key_verifier  # type: ignore[attr-defined]
        verifier.cache = TtlCache(TTL_S, 100, clock=clock)
        yield Api(client), clock


def _key_of_another_process(db_url: str) -> tuple[Database, int, dict[str, str]]:
    """An ingest+read key made through a second connection pool, as another process would."""
    other_process = Database(db_url)
    with other_process.write() as s:
        row, key = create_key(s, "default", ["ingest", "read"], name="stand")
    return other_process, row.id, {"Authorization": f"Bearer {key}"}


def test_a_key_revoked_elsewhere_stops_working_within_the_ttl(api_clocked: tuple[Api, FakeClock], db_url: str) -> None:
    api, clock = api_clocked
    api.setup_actuator()
    other_process, row_id, as_key = _key_of_another_process(db_url)
    assert api.c.get("/v1/aircraft", headers=as_key).status_code == 200
    with other_process.write() as s:
        assert revoke_key(s, row_id)
    other_process.dispose()
    # Remembered at most TTL_S: past it the key is read again and refused.
    clock.now += TTL_S + 0.01
    r = api.c.get("/v1/aircraft", headers=as_key)
    assert r.status_code == 401, r.text
    assert r.json()["error"] == "Unauthorized"
    r = api.c.post("/v1/aircraft/N1/actuators/ema1/telemetry", json=_one_sample(1), headers=as_key)
    assert r.status_code == 401, r.text


def test_a_scope_removed_elsewhere_is_refused_within_the_ttl(api_clocked: tuple[Api, FakeClock], db_url: str) -> None:
    api, clock = api_clocked
    api.setup_actuator()
    other_process, row_id, as_key = _key_of_another_process(db_url)
    path = "/v1/aircraft/N1/actuators/ema1/telemetry"
    assert api.c.post(path, json=_one_sample(1), headers=as_key).status_code == 202
    with other_process.write() as s:
        assert set_scopes(s, row_id, ["read"])
    other_process.dispose()
    clock.now += TTL_S + 0.01
    r = api.c.post(path, json=_one_sample(2), headers=as_key)
    assert r.status_code == 403, r.text
    assert api.c.get("/v1/aircraft", headers=as_key).status_code == 200


def test_unknown_keys_are_not_remembered(api_clocked: tuple[Api, FakeClock], db_url: str) -> None:
    api, _ = api_clocked
    key = "fh_not-yet-created-key-0123456789"
    assert api.c.get("/v1/aircraft", headers={"Authorization": f"Bearer {key}"}).status_code == 401
    other_process = Database(db_url)
    with other_process.write() as s:
        create_key(s, "default", ["read"], name="late", key=key)
    other_process.dispose()
    # No clock change: a refusal was not cached, so the new key works at once.
    assert api.c.get("/v1/aircraft", headers={"Authorization": f"Bearer {key}"}).status_code == 200


# ----------------------------------------------------------------------------- actuators
def test_an_actuator_deleted_by_this_process_takes_no_more_batches(api_clocked: tuple[Api, FakeClock]) -> None:
    api, _ = api_clocked
    api.setup_actuator()
    path = "/v1/aircraft/N1/actuators/ema1/telemetry"
    assert api.post(path, json=_one_sample(1)).status_code == 202
    assert len(api.app.state.actuator_lookup.cache) == 1  # remembered from here on
    assert api.c.delete("/v1/aircraft/N1/actuators/ema1", headers=api.h).status_code == 200
    r = api.post(path, json=_one_sample(2))
    assert r.status_code == 410, r.text
    assert r.json()["error"] == "Gone"


def test_an_actuator_deleted_by_another_process_takes_no_more_batches(
    api_clocked: tuple[Api, FakeClock], db_url: str
) -> None:
    api, _ = api_clocked
    api.setup_actuator()
    path = "/v1/aircraft/N1/actuators/ema1/telemetry"
    assert api.post(path, json=_one_sample(1)).status_code == 202
    assert len(api.app.state.actuator_lookup.cache) == 1
    other_process = Database(db_url)
    with other_process.write() as s:
        ac = fleet.get_aircraft(s, api.app.state.key_verifier.verify(api.h["Authorization"]).operator_id, "N1")
        fleet.delete_aircraft(s, ac)
    r = api.post(path, json=_one_sample(2))
    assert r.status_code in (404, 410), r.text
    # Purged and registered anew under the same names: the batch goes to the new actuator.
    with other_process.write() as s:
        fleet.purge_deleted(s, retention_s=-3600.0)
    other_process.dispose()
    api.setup_actuator()
    r = api.post(path, json=_one_sample(3))
    assert r.status_code == 202, r.text
    assert r.json()["seq"] == 1
    logged = api.get(f"{path}?order=asc").json()
    assert logged["t_s"] == [3.0]
