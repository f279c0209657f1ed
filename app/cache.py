"""A small, bounded, short-lived cache of database look-ups made on every request (API keys,
the actuator a telemetry path names), so that a request that finds its answer here needs no
database round trip and no worker thread.

An entry lives at most ``ttl_s`` seconds after it was read from the database: that is the bound
on how long a change made by another process (a key revoked with ``fleethealth keys revoke``)
may go unseen. A change made in this process calls :meth:`TtlCache.invalidate`, and a look-up
that read the database before such an invalidation does not store its (possibly stale) answer
(generation count). ``ttl_s = 0`` turns the cache off. Safe to use from the event loop and from
worker threads at once.

Memory: at most ``max_entries`` entries, and none older than ``ttl_s`` once the cache is used
again. Entries are kept in the order they expire (each is stored at the end, with the same
``ttl_s``), so every call drops the expired ones from the front, a constant cost per call on
average: the entry of a stream gone idle leaves with the first use of the cache ``ttl_s`` after
it was stored (docs/scaling.md, "Memory per idle stream").
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class TtlCache(Generic[K, V]):
    def __init__(
        self, ttl_s: float, max_entries: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: OrderedDict[K, tuple[float, V]] = OrderedDict()
        self._generation = 0

    def get(self, key: K) -> V | None:
        """The entry for ``key`` if it was read less than ``ttl_s`` ago, else None."""
        with self._lock:
            self._drop_expired(self._clock())
            found = self._entries.get(key)
            return None if found is None else found[1]

    def _drop_expired(self, now: float) -> None:
        """Drop the entries expired at ``now``: they are the first ones (stored in expiry order)."""
        entries = self._entries
        while entries:
            key, (expires_at, _) = next(iter(entries.items()))
            if now < expires_at:
                return
            del entries[key]

    def generation(self) -> int:
        """Take this before reading the database, and hand it to :meth:`put`."""
        with self._lock:
            return self._generation

    def put(self, key: K, value: V, generation: int) -> None:
        """Store ``value``, read from the database after :meth:`generation` returned
        ``generation``; dropped if an invalidation came in between (the value may predate it).
        The oldest entry makes room when the cache is full."""
        if self.ttl_s <= 0:
            return
        with self._lock:
            now = self._clock()
            self._drop_expired(now)
            if generation != self._generation:
                return
            self._entries.pop(key, None)
            self._entries[key] = (now + self.ttl_s, value)
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)

    def invalidate(self, key: K | None = None) -> None:
        """Forget ``key`` (every entry when None); look-ups under way do not store theirs."""
        with self._lock:
            self._drop_expired(self._clock())
            self._generation += 1
            if key is None:
                self._entries.clear()
            else:
                self._entries.pop(key, None)

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
