"""What the look-up caches (app/cache.py) keep resident: never more than ``max_entries``, and no
entry past its ``ttl_s`` once the cache is used again, so that a stream gone idle holds nothing
in them (docs/scaling.md, "Memory per idle stream"). A fake clock: nothing waits."""

from __future__ import annotations

import random

from app.cache import TtlCache
from tests.app.conftest import FakeClock

TTL_S = 5.0


def test_idle_entries_leave_at_the_next_use_after_their_ttl() -> None:
    clock = FakeClock()
    cache: TtlCache[str, int] = TtlCache(TTL_S, max_entries=1000, clock=clock)
    for i in range(500):  # a registration burst: 500 streams, each looked up once
        cache.put(f"idle-{i}", i, cache.generation())
    clock.now += TTL_S / 2
    cache.put("live", -1, cache.generation())
    assert len(cache) == 501
    clock.now += TTL_S / 2  # the burst's entries have expired, the live stream's has not
    assert cache.get("live") == -1
    assert len(cache) == 1
    clock.now += TTL_S
    assert cache.get("other") is None
    assert len(cache) == 0


def test_a_reread_entry_moves_behind_the_ones_expiring_sooner() -> None:
    clock = FakeClock()
    cache: TtlCache[str, int] = TtlCache(TTL_S, max_entries=10, clock=clock)
    cache.put("a", 1, cache.generation())
    clock.now += 1.0
    cache.put("b", 2, cache.generation())
    clock.now += 1.0
    cache.put("a", 3, cache.generation())  # stored again: now expires after "b"
    clock.now += TTL_S - 1.5
    assert cache.get("b") == 2
    clock.now += 1.0  # "b" expired, "a" (stored 1 s later than "b") not yet
    assert cache.get("a") == 3
    assert len(cache) == 1


def test_size_and_age_bounds_hold_under_any_sequence_of_calls() -> None:
    rng = random.Random(14)
    clock = FakeClock()
    max_entries = 16
    cache: TtlCache[int, int] = TtlCache(TTL_S, max_entries=max_entries, clock=clock)
    stored: dict[int, tuple[float, int]] = {}  # the model: key -> (stored at, value)
    for step in range(5000):
        clock.now += rng.choice((0.0, 0.01, 0.3, 1.0, 7.0))
        key = rng.randrange(40)
        op = rng.random()
        if op < 0.5:
            cache.put(key, step, cache.generation())
            stored[key] = (clock.now, step)
        elif op < 0.95:
            got = cache.get(key)
            if got is not None:  # a hit is the latest value stored, within its ttl
                assert stored[key][1] == got
                assert clock.now - stored[key][0] < TTL_S
        else:
            cache.invalidate(key)
            stored.pop(key, None)
        assert len(cache) <= max_entries
        entries = cache._entries  # what is resident after the call
        assert all(clock.now - stored[k][0] < TTL_S for k in entries)
        expiries = [e for e, _ in entries.values()]
        assert expiries == sorted(expiries)


def test_ttl_zero_keeps_nothing() -> None:
    cache: TtlCache[str, int] = TtlCache(0.0, max_entries=10, clock=FakeClock())
    cache.put("a", 1, cache.generation())
    assert len(cache) == 0
