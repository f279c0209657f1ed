"""Estimator states kept in memory between applies, so that an apply does not parse the state
(and the config) it stored itself one transaction earlier.

The store stays the truth: an entry is used only when the row the apply just read (inside its
transaction, under the stream's claim) holds exactly the bytes the entry was made from, state
and config alike, and the kind still reads states of the version it held. Whatever else
happened to the row since (another process applied the stream, an admin rewind reset it, a
maintenance action started a new baseline, a replay rewrote it, or this process's own
transaction rolled back after the entry was made) changed those bytes, and the state is read
from the row again. An entry is taken out when it is used and put back only
with the new state, so a step that failed half-way leaves nothing behind.

Parsing a state costs from about 0.1 ms (FAKF, a 1 KB JSON document) to several ms (the
STMMAE bank and DARR, tens to hundreds of KB); comparing the bytes costs microseconds. The
entries are bounded in number and in bytes (least recently used go first): the streams that
apply often stay, an idle fleet costs nothing.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.processing.orchestration import Runner
from estimators.registry import ESTIMATORS

#: At most this many estimator states are held (about the streams that apply continually).
MAX_ENTRIES = 256
#: ... and at most this many bytes of stored state (their in-memory form is about as large).
MAX_BYTES = 16 * 2**20


@dataclass(frozen=True)
class _Entry:
    blob: bytes
    raw_config: Mapping[str, Any]
    config: Any
    state: Any
    # The kind's STATE_VERSION when the entry was made: a state is never taken past a change
    # of the layout the kind reads (the row is read, and replayed if unreadable).
    version: int
    # Stepped from a state read back from the store (or from such an entry): this build's
    # states of the stream are known to read back. A state first written here (a new stream)
    # is read from the row once, so that one this build cannot read back is found at once.
    verified: bool


class HotStates:
    """Parsed estimator states by (stream, estimator), valid only for the bytes they came from."""

    def __init__(self, max_entries: int = MAX_ENTRIES, max_bytes: int = MAX_BYTES) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple[int, str], _Entry] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def take(
        self, actuator_pk: int, name: str, blob: bytes | None, raw_config: Mapping[str, Any]
    ) -> tuple[Any, Any] | None:
        """``(config, state)`` parsed from exactly ``blob`` and ``raw_config`` (the row as read
        now), else None; the entry is removed either way."""
        with self._lock:
            entry = self._items.pop((actuator_pk, name), None)
            if entry is not None:
                self._bytes -= len(entry.blob)
            if (entry is None or blob is None or entry.blob != blob or entry.raw_config != raw_config
                    or entry.version != ESTIMATORS[name].STATE_VERSION or not entry.verified):
                self.misses += 1
                return None
            self.hits += 1
            return entry.config, entry.state

    def put(
        self, actuator_pk: int, name: str, blob: bytes, raw_config: Mapping[str, Any], config: Any, state: Any,
        *, verified: bool = True,
    ) -> None:
        """Remember the state just dumped to ``blob`` (before the commit: an entry whose commit
        fails no longer matches the row, and is not used)."""
        if len(blob) > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop((actuator_pk, name), None)
            if old is not None:
                self._bytes -= len(old.blob)
            self._items[(actuator_pk, name)] = _Entry(blob, dict(raw_config), config, state,
                                                      ESTIMATORS[name].STATE_VERSION, verified)
            self._bytes += len(blob)
            while len(self._items) > self.max_entries or self._bytes > self.max_bytes:
                _, gone = self._items.popitem(last=False)
                self._bytes -= len(gone.blob)

    def forget(self, actuator_pk: int) -> None:
        with self._lock:
            for key in [k for k in self._items if k[0] == actuator_pk]:
                self._bytes -= len(self._items.pop(key).blob)

    def __len__(self) -> int:
        return len(self._items)


def runner_of(
    hot: HotStates | None,
    actuator_pk: int,
    name: str,
    raw_config: Mapping[str, Any],
    blob: bytes | None,
    status: str,
    reasons: tuple[str, ...],
    diagnosis_t_s: float | None,
    diagnosis: dict[str, Any] | None,
) -> Runner | None:
    """The runner from the held state when it matches the row, else None (parse the row)."""
    if hot is None:
        return None
    held = hot.take(actuator_pk, name, blob, raw_config)
    if held is None:
        return None
    config, state = held
    return Runner(name, ESTIMATORS[name], config, state, status, reasons, diagnosis_t_s, diagnosis)
