"""Batches this process is committing to the telemetry log, kept decoded until the processor
applies them, so that a fresh batch is not decoded again from its stored payload.

Only a shortcut: the log stays the source of truth. A batch the processor does not find here
(another process logged it, the bound was reached when it was logged, or a failed apply took
it) is decoded from the log; the values are the same either way (the log's float64 columns are
lossless). At the bound (``MAX_SAMPLES``) a new batch is not held, unless the oldest held one is
stale (``STALE_S``: presumably applied by another process) and gives way: the processor applies
the oldest batches first, so under a backlog the held ones are those applied next.

The log writer puts a group's batches *before* its commit (:meth:`RecentBatches.put`, tentative)
and confirms them once the commit returned (:meth:`RecentBatches.confirm`) or drops them when it
failed (:meth:`RecentBatches.drop`). On PostgreSQL the commit's ``NOTIFY`` can wake the processor
before the writer thread runs again: a batch put only after the commit would then be decoded from
the log, and its held copy would stay until newer batches push it out. A processor that finds a
tentative entry waits for the writer's verdict (the commit has returned by the time the processor
sees the row: the verdict follows within the writer's next few statements, at most
``CONFIRM_WAIT_S``); so an entry is only ever taken for the batch whose commit put it, never for
another batch a rolled-back append's position was given to. Entries are keyed by stream, ``seq``
and ``batch_id`` (a row whose batch id differs takes nothing).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from prometheus_client import Counter

from estimators.base import Batch

TAKEN = Counter(
    "fleethealth_recent_batches_total",
    "Logged batches the apply looked for decoded in memory: found (hit) or decoded from the log "
    "(miss); and batches not held because the bound was reached (not_held)",
    ["outcome"],
)
_HIT, _MISS, _NOT_HELD = TAKEN.labels("hit"), TAKEN.labels("miss"), TAKEN.labels("not_held")

# Upper bound of the samples held (x channels x 8 bytes): a backlog beyond it is read from the log.
MAX_SAMPLES = 262_144
#: A confirmed entry held this long is presumed applied elsewhere (another process's worker, a
#: deleted stream): it gives way to a new batch when the bound is reached.
STALE_S = 10.0
#: Longest a taker waits for the writer's verdict on a tentative entry (then reads the log).
CONFIRM_WAIT_S = 1.0

Key = tuple[int, int]


@dataclass
class _Entry:
    batch_id: str
    batch: Batch
    held_since: float
    confirmed: bool = False


class RecentBatches:
    def __init__(self, max_samples: int = MAX_SAMPLES, confirm_wait_s: float = CONFIRM_WAIT_S,
                 stale_s: float = STALE_S) -> None:
        self.max_samples = max_samples
        self.confirm_wait_s = confirm_wait_s
        self.stale_s = stale_s
        self._cond = threading.Condition()
        self._items: OrderedDict[Key, _Entry] = OrderedDict()
        self._samples = 0
        # Counters of take(): found here / decoded from the log (bench and tests read them).
        self.hits = 0
        self.misses = 0

    def put(self, actuator_pk: int, seq: int, batch_id: str, t_s: np.ndarray,
            channels: dict[str, np.ndarray], end_of_run: bool) -> Key | None:
        """Hold a batch about to be committed (tentative until :meth:`confirm`); its key, or
        None when it is not held (the bound is reached by fresh entries, or it alone exceeds it)."""
        n = int(t_s.shape[0])
        if n > self.max_samples:
            return None
        # Writeable, contiguous float64 (what the kernels were warmed with), as decoded from the log.
        batch = Batch(
            t_s=np.require(t_s, np.float64, ["C", "W"]),
            channels={k: np.require(v, np.float64, ["C", "W"]) for k, v in channels.items()},
            end_of_run=end_of_run,
        )
        key = (actuator_pk, seq)
        now = time.monotonic()
        with self._cond:
            old = self._items.pop(key, None)
            if old is not None:
                self._samples -= int(old.batch.t_s.shape[0])
            # Full: stale entries give way; fresh ones stay, and the new batch is not held. The
            # processor applies the oldest first, so under a backlog the held batches are the
            # next ones applied (evicting the oldest instead would drop each batch just before
            # its apply, and a steady backlog above the bound would never hit).
            while self._samples + n > self.max_samples and self._items:
                oldest = next(iter(self._items.values()))
                if not oldest.confirmed or now - oldest.held_since < self.stale_s:
                    _NOT_HELD.inc()
                    return None
                self._items.popitem(last=False)
                self._samples -= int(oldest.batch.t_s.shape[0])
            self._items[key] = _Entry(batch_id, batch, now)
            self._samples += n
            if old is not None:
                self._cond.notify_all()  # a taker waiting on the replaced entry looks again
        return key

    def confirm(self, keys: Iterable[Key]) -> None:
        """The commit that logged these batches returned: they may be taken."""
        with self._cond:
            for key in keys:
                entry = self._items.get(key)
                if entry is not None:
                    entry.confirmed = True
            self._cond.notify_all()

    def drop(self, keys: Iterable[Key]) -> None:
        """The commit failed: these batches were not logged (their positions may go to others)."""
        with self._cond:
            for key in keys:
                entry = self._items.pop(key, None)
                if entry is not None:
                    self._samples -= int(entry.batch.t_s.shape[0])
            self._cond.notify_all()

    def take(self, actuator_pk: int, seq: int, batch_id: str) -> Batch | None:
        """The batch logged at ``seq`` with ``batch_id``, if this process committed it and still
        holds it (removed either way); None: decode it from the log."""
        key = (actuator_pk, seq)
        with self._cond:
            entry = self._items.get(key)
            if entry is not None and not entry.confirmed:
                deadline = time.monotonic() + self.confirm_wait_s
                while entry is not None and not entry.confirmed:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                    entry = self._items.get(key)
            if entry is None or not entry.confirmed:
                self.misses += 1
                _MISS.inc()
                return None
            del self._items[key]
            self._samples -= int(entry.batch.t_s.shape[0])
            if entry.batch_id != batch_id:  # not the batch logged there: let it go, read the log
                self.misses += 1
                _MISS.inc()
                return None
            self.hits += 1
            _HIT.inc()
            return entry.batch

    def __len__(self) -> int:
        return len(self._items)
