"""SQLite: the processor in a process of its own, a child of ``serve`` (``APPLY_PROCESS=on``).

One process does its Python work under one interpreter lock: with the processor inside
``serve``, every apply holds it while requests wait (docs/benchmarks.md). Here ``serve`` keeps
the HTTP and WebSocket work and the log writer, and a child process applies the streams; the
two share the SQLite file. Neither polls: writers of both processes take the cross-process
write lock (:class:`app.db.FileWriteLock`, a blocking ``flock``) after their own in-process
one, and the two exchange frames over a Unix socket pair (a 4-byte length, a kind byte, the
body):

* ``serve`` -> child: ``S`` the settings (JSON), first; ``L`` after each log commit, the streams
  to wake (``pk,pk,...``, as ``LISTEN/NOTIFY``'s ``logged`` channel on PostgreSQL); ``W``/``U``
  a stream that got its first / lost its last WebSocket connection in ``serve``;
* child -> ``serve``: after each apply commit, ``R`` the results of a watched stream (pickled
  :class:`~app.processing.messages.BatchResult` objects, pushed to its connections as this process
  pushes its own) and ``A`` the payloads of the applied channel (:mod:`app.processing.wakeups`:
  applied mark and fleet events, ``"r": 1`` when the results went ahead; or a failure); ``K``
  the kernel warm-up's state (for ``/readyz``) until every kind is ready; ``M`` every second,
  its ``fleethealth_*`` metrics, which ``serve``'s ``/metrics`` adds to its own
  (:func:`merged_families`; its threads named ``apply:<thread>``).

A message is sent after its commit and only then. Messages are not durable and need not be:
the child scans for pending streams when it starts and every ``processor_scan_interval_s``;
``serve`` re-reads its waiters' marks and sends its watched streams whenever it starts a child.
A connection that misses a push reads its results back from the store, as for any apply made
elsewhere. If the child dies (even SIGKILL: the kernel releases its ``flock`` and SQLite rolls
its transaction back), ``serve`` starts another, which applies from the last committed state:
nothing is lost or applied twice. The child exits when the socket closes (``serve`` ended,
however it ended). Pickle crosses only this private socket pair between two processes of the
same program.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import IO, Any

import orjson
from prometheus_client import Counter
from prometheus_client.metrics_core import Metric
from prometheus_client.samples import Sample

from app.config import Settings
from app.processing import wakeups

log = logging.getLogger("fleethealth.apply_process")

#: Frames not yet taken by the child's socket: past this many bytes, new wake-ups are dropped
#: (the child is stuck or starting; its scan finds the streams).
MAX_PENDING_BYTES = 1 << 20
RESTART_BACKOFF_S = (0.5, 30.0)
#: A child that ran this long before it died is restarted without back-off.
HEALTHY_RUN_S = 30.0
STARTS = Counter("fleethealth_apply_process_starts_total",
                 "Apply processes started by this serve process (SQLite, APPLY_PROCESS=on): 1 + restarts")
_HEADER = struct.Struct("!IB")


def frame(kind: bytes, body: bytes) -> bytes:
    return _HEADER.pack(len(body), kind[0]) + body


def frames(reader: IO[bytes]) -> Iterator[tuple[bytes, bytes]]:
    """(kind, body) of each frame until the socket closes."""
    while True:
        header = reader.read(_HEADER.size)
        if len(header) < _HEADER.size:
            return
        n, kind = _HEADER.unpack(header)
        body = reader.read(n)
        if len(body) < n:
            return
        yield bytes([kind]), body


class ApplyProcess:
    """``serve``'s side: starts the child, keeps it running, sends it wake-ups and the streams
    watched here, and hands its messages to the callbacks (from its own thread)."""

    def __init__(
        self,
        settings: Settings,
        *,
        kinds: Sequence[str],
        on_applied: Callable[[int, int, list[dict[str, Any]], bool], None],
        on_failed: Callable[[int, str], None],
        on_results: Callable[[int, list[Any]], None],
        on_restart: Callable[[], object],
        watched: Callable[[], Iterable[int]] = lambda: (),
        command: Sequence[str] | None = None,
    ) -> None:
        self.settings = settings
        self.on_applied = on_applied
        self.on_failed = on_failed
        self.on_results = on_results
        self.on_restart = on_restart
        self.watched = watched
        self.command = list(command or [sys.executable, "-m", "app.processing.apply_process"])
        self._kernels: dict[str, dict[str, Any]] = {k: {"status": "waiting"} for k in kinds}
        self._metrics: list[Any] = []
        self.kernels_done = threading.Event()
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._pending = b""
        self._proc: subprocess.Popen[bytes] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ serve's side
    def start(self) -> None:
        self._spawn()
        self._thread = threading.Thread(target=self._supervise, name="fleethealth-apply-process", daemon=True)
        self._thread.start()

    def notify_many(self, actuator_pks: Sequence[int]) -> None:
        """Wake the streams in the child; never blocks (a wake-up the socket cannot take now
        waits in a bounded buffer, or is dropped for the child's scan to find)."""
        if actuator_pks:
            self._send(frame(b"L", ",".join(map(str, actuator_pks)).encode()))

    def watch(self, actuator_pk: int, watched: bool) -> None:
        """A stream got its first (True) or lost its last WebSocket connection here: the child
        pushes its results (or stops)."""
        self._send(frame(b"W" if watched else b"U", str(actuator_pk).encode()))

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """The child's kernel warm-up, as ``KernelWarmup.snapshot`` (``/readyz``)."""
        with self._lock:
            return {k: dict(v) for k, v in self._kernels.items()}

    def metric_families(self) -> list[Any]:
        """The child's ``fleethealth_*`` metrics as last reported: ``[name, type, help,
        [[sample, labels, value], ...]]`` per family."""
        with self._lock:
            return self._metrics

    def stop(self, timeout_s: float = 10.0) -> None:
        """Close the socket (the child finishes its transaction and exits), then wait for it;
        killed if it does not exit in time."""
        self._stop.set()
        with self._lock:
            sock, self._sock = self._sock, None
        if sock is not None:
            # Shut down first: the reader thread's file object keeps the descriptor open past
            # close(), and the child would not see the end of its socket until it was killed.
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()
        proc = self._proc
        if proc is not None:
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("the apply process did not exit within %.1f s; killing it", timeout_s)
                proc.kill()
                proc.wait(5)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _send(self, data: bytes) -> None:
        with self._lock:
            sock = self._sock
            if sock is None:
                return  # between two children: the next one's first scan finds the streams
            if len(self._pending) > MAX_PENDING_BYTES:
                # Dropped whole (the buffer may end inside a frame already begun: it is kept).
                log.warning("the apply process is not reading its wake-ups; dropping them (its scan catches up)")
                return
            data = self._pending + data
            try:
                n = sock.send(data, socket.MSG_DONTWAIT)
            except BlockingIOError:
                n = 0
            except OSError:
                return  # the child is gone; the supervisor starts another
            self._pending = data[n:]

    def _spawn(self) -> None:
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            env = {**os.environ, "FLEETHEALTH_APPLY_PROCESS_FD": str(child.fileno())}
            self._proc = subprocess.Popen(self.command, env=env, pass_fds=(child.fileno(),),
                                          stdin=subprocess.DEVNULL)
        finally:
            child.close()
        STARTS.inc()
        parent.sendall(frame(b"S", self.settings.model_dump_json().encode())
                       + b"".join(frame(b"W", str(pk).encode()) for pk in self.watched()))
        with self._lock:
            self._sock, self._pending = parent, b""
        log.info("apply process %d started", self._proc.pid)

    def _supervise(self) -> None:
        delay = RESTART_BACKOFF_S[0]
        while True:
            started = time.monotonic()
            sock = self._sock
            if sock is not None:
                self._read(sock)
            proc = self._proc
            assert proc is not None
            if self._stop.is_set():
                return
            code = proc.wait()
            with self._lock:
                if self._sock is sock:
                    self._sock = None
            if sock is not None:
                sock.close()
            if time.monotonic() - started > HEALTHY_RUN_S:
                delay = RESTART_BACKOFF_S[0]
            log.error("the apply process exited with code %s; starting another in %.1f s", code, delay)
            if self._stop.wait(delay):
                return
            delay = min(delay * 2, RESTART_BACKOFF_S[1])
            try:
                self._spawn()
            except Exception:
                log.exception("starting the apply process failed")
                continue
            try:
                self.on_restart()  # applies the dead child committed but did not announce
            except Exception:
                log.exception("re-reading the waiters' marks failed")

    def _read(self, sock: socket.socket) -> None:
        try:
            with sock.makefile("rb") as reader:
                for kind, body in frames(reader):
                    self._dispatch(kind, body)
        except (OSError, ValueError):
            return  # closed by stop(), or the child went away

    def _dispatch(self, kind: bytes, body: bytes) -> None:
        try:
            if kind == b"A":
                wakeups.dispatch_applied(body, wakeups.ORIGIN, self.on_applied, self.on_failed)
            elif kind == b"R":
                pk, items = pickle.loads(body)  # noqa: S301 (our own child, a private socket pair)
                self.on_results(int(pk), items)
            elif kind == b"M":
                families = orjson.loads(body)
                with self._lock:
                    self._metrics = families
            elif kind == b"K":
                snap = orjson.loads(body)
                with self._lock:
                    self._kernels = snap
                if all(v.get("status") in ("ready", "failed") for v in snap.values()):
                    self.kernels_done.set()
            else:
                log.warning("unknown message %r from the apply process", kind)
        except Exception:
            log.exception("bad message %r from the apply process", kind)


# ---------------------------------------------------------------------- the child
class _Pipe:
    """The child's end: sends whole frames (from any thread)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._lock = threading.Lock()

    def send(self, data: bytes) -> None:
        with self._lock:
            self.sock.sendall(data)


def child_main(fd: int) -> int:
    """The apply process: a processor and its kernel warm-up, driven by ``serve``'s socket."""
    from app.db import Database
    from app.kernels import KernelWarmup
    from app.processing.processor import Processor
    from app.processing.service import ApplyResult
    from app.system import threads
    from estimators.registry import ESTIMATORS

    threads.register()
    sock = socket.socket(fileno=fd)
    reader = sock.makefile("rb")
    incoming = frames(reader)
    first = next(incoming, None)
    if first is None or first[0] != b"S":
        print("apply process: no settings from serve", file=sys.stderr)
        return 2
    settings = Settings.model_validate_json(first[1])
    _log_to_stderr()
    pipe = _Pipe(sock)
    watched: set[int] = set()

    def push(res: ApplyResult) -> bool:
        if res.actuator_pk not in watched:
            return False
        pipe.send(frame(b"R", pickle.dumps((res.actuator_pk, res.applied), protocol=pickle.HIGHEST_PROTOCOL)))
        return True

    db = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)
    kernels = KernelWarmup(list(ESTIMATORS), processes=settings.warm_kernels_processes,
                           enabled=settings.warm_kernels)
    processor = Processor(
        db, settings, origin=wakeups.ORIGIN, ready_kinds=kernels.applicable_kinds,
        announce=lambda payloads: pipe.send(b"".join(frame(b"A", p.encode()) for p in payloads)),
        push_results=push, in_lock_applies=False,
    )
    stop = threading.Event()

    def _report_kernels() -> None:
        try:
            pipe.send(frame(b"K", orjson.dumps(kernels.snapshot())))
        except OSError:
            stop.set()

    def _kind_ready(_kind: str) -> None:
        _report_kernels()
        processor.recover()  # wake the streams that waited for this kind

    kernels.on_ready = _kind_ready

    def _read() -> None:
        try:
            for kind, body in incoming:
                if kind == b"L" and body:
                    processor.notify_many([int(p) for p in body.split(b",")])
                elif kind == b"W":
                    watched.add(int(body))
                elif kind == b"U":
                    watched.discard(int(body))
        except (OSError, ValueError):
            log.exception("reading serve's messages failed")
        stop.set()  # serve closed the socket (it stopped, or died)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    processor.start()
    kernels.start()
    _report_kernels()
    threading.Thread(target=_read, name="fleethealth-apply-wakeups", daemon=True).start()
    try:
        while not stop.wait(1.0):
            if not kernels.done.is_set():
                _report_kernels()  # progress ("compiling", its seconds) for /readyz
            try:
                pipe.send(frame(b"M", orjson.dumps(own_families())))
            except OSError:
                stop.set()
            if not processor.running:
                log.error("the processor thread stopped")
                return 1
    finally:
        kernels.stop()
        processor.stop(timeout=settings.shutdown_timeout_s)
        db.dispose()
    return 0


def own_families() -> list[Any]:
    """This process's ``fleethealth_*`` metrics, its threads named ``apply:<thread>``."""
    from prometheus_client.registry import REGISTRY

    out = []
    for fam in REGISTRY.collect():
        if not fam.name.startswith("fleethealth_"):
            continue
        samples = []
        for smp in fam.samples:
            labels = dict(smp.labels)
            if fam.name == "fleethealth_thread_cpu_seconds" and "thread" in labels:
                labels["thread"] = "apply:" + labels["thread"]
            samples.append([smp.name, labels, smp.value])
        out.append([fam.name, fam.type, fam.documentation, samples])
    return out


def merged_families(own: Iterable[Metric], child: list[Any]) -> list[Metric]:
    """This process's metric families with the child's added: a sample both report is summed
    (counters, histograms and the processor's gauges count across the two processes; a
    ``_created`` time is the earlier one); the child's other samples and families are added."""
    merged: dict[str, Metric] = {}
    for fam in own:
        merged[fam.name] = fam
    for name, typ, doc, samples in child:
        if name not in merged:
            merged[name] = Metric(name, doc, typ)
        fam = merged[name]
        index = {(s.name, tuple(sorted(s.labels.items()))): i for i, s in enumerate(fam.samples)}
        for sample_name, labels, value in samples:
            key = (sample_name, tuple(sorted(labels.items())))
            i = index.get(key)
            if i is None:
                fam.samples.append(Sample(sample_name, labels, value))
                index[key] = len(fam.samples) - 1
                continue
            old = fam.samples[i]
            both = min(old.value, value) if sample_name.endswith("_created") else old.value + value
            fam.samples[i] = old._replace(value=both)
    return list(merged.values())


def _log_to_stderr() -> None:
    logger = logging.getLogger("fleethealth")
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(levelname)s:     %(name)s[apply]: %(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)


if __name__ == "__main__":
    sys.exit(child_main(int(os.environ["FLEETHEALTH_APPLY_PROCESS_FD"])))
