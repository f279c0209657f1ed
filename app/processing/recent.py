"""Batches this process has just committed to the telemetry log, kept decoded until the
processor applies them, so that a fresh batch is not decoded again from its stored payload.

Only a shortcut: the log stays the source of truth. A batch the processor does not find here
(another process logged it, it was evicted, or a failed apply took it) is decoded from the log;
the values are the same either way (the log's float64 columns are lossless).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from estimators.base import Batch

# Upper bound of the samples held (x channels x 8 bytes): a backlog beyond it is read from the log.
MAX_SAMPLES = 262_144


class RecentBatches:
    def __init__(self, max_samples: int = MAX_SAMPLES) -> None:
        self.max_samples = max_samples
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple[int, int], Batch] = OrderedDict()
        self._samples = 0

    def put(self, actuator_pk: int, seq: int, t_s: np.ndarray, channels: dict[str, np.ndarray],
            end_of_run: bool) -> None:
        # Writeable, contiguous float64 (what the kernels were warmed with), as decoded from the log.
        batch = Batch(
            t_s=np.require(t_s, np.float64, ["C", "W"]),
            channels={k: np.require(v, np.float64, ["C", "W"]) for k, v in channels.items()},
            end_of_run=end_of_run,
        )
        n = int(batch.t_s.shape[0])
        if n > self.max_samples:
            return
        with self._lock:
            self._items[(actuator_pk, seq)] = batch
            self._samples += n
            while self._samples > self.max_samples:
                _, old = self._items.popitem(last=False)
                self._samples -= int(old.t_s.shape[0])

    def take(self, actuator_pk: int, seq: int) -> Batch | None:
        with self._lock:
            batch = self._items.pop((actuator_pk, seq), None)
            if batch is not None:
                self._samples -= int(batch.t_s.shape[0])
            return batch

    def __len__(self) -> int:
        return len(self._items)
