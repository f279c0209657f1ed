"""Estimator kernels prepared kind by kind in the background while the service already answers.

numba compiles a kind's kernels on first use: tens of seconds per kind on a cold cache, a fraction
of a second once its on-disk cache (``cache=True``) holds them. At start-up :class:`KernelWarmup`
prepares every estimator kind, cheapest and most used first (:data:`COMPILE_ORDER`):

* a kind compiled before with the same sources and numba (a stamp file beside numba's cache
  says so) is loaded from the cache by the server itself, in a thread (about a second);
* otherwise, with ``processes > 0`` (the default), up to that many child processes
  (``python -m app.kernels KIND``) compile kinds at once and fill numba's cache; the server then
  loads each finished kind from the cache and marks it ready;
* with ``processes == 0`` the server compiles each kind itself, in a thread.

A child compiles a kind holding an exclusive lock on a file beside the stamps
(``fleethealth-kernels-KIND.lock``): several processes starting at once on a cold cache (an
API and its workers, a test session) compile each kind once; the others wait for the lock and
then load the kind from the cache just filled (a lock dies with its holder, however it died).

Children because a SIGTERM must end the server within seconds at any moment: a compile running
in a thread of the server cannot be interrupted, a child is killed at once; and numba's compiler,
mostly Python, would otherwise hold the server's interpreter lock while requests wait. A child
whose parent dies (even by SIGKILL) sees its stdin close and exits.

A kind is *ready* once the server has its kernels loaded; the processor applies a stream only
when every estimator attached to it is of a ready kind (:meth:`KernelWarmup.applicable_kinds`),
so no apply pays a compile and each kind's streams start as soon as that kind is ready. Batches
are accepted, and durable, meanwhile. A kind whose warm-up failed is reported ``failed`` by
``/readyz`` with the reason, and its streams are applied anyway (an apply then compiles on
demand, or fails the stream with the error: never silently pending).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

log = logging.getLogger("fleethealth.kernels")

#: Kinds compiled first, in this order (measured cost, ``bench/bench_warmup.py``, and the demo's
#: kinds before the others); kinds not listed follow in registry order.
COMPILE_ORDER = ("fakf", "deterioration_ekf", "stmmae", "darr_fekf")
#: How often the coordinator looks at its children (also bounds how late a stop is seen).
POLL_S = 0.1
#: Last characters of a failed child's stderr kept for the reason.
ERROR_TAIL_CHARS = 400

KindState = Literal["waiting", "compiling", "loading", "ready", "failed"]


@dataclass
class KindStatus:
    """Where one kind's warm-up stands (monotonic clock seconds)."""

    state: KindState = "waiting"
    started_s: float | None = None
    finished_s: float | None = None
    error: str | None = None

    def public(self, now_s: float) -> dict[str, Any]:
        out: dict[str, Any] = {"status": self.state}
        if self.started_s is not None:
            out["seconds"] = round((self.finished_s or now_s) - self.started_s, 1)
        if self.error is not None:
            out["error"] = self.error
        return out


def ordered_kinds(kinds: Sequence[str]) -> list[str]:
    """``kinds`` in compile order: :data:`COMPILE_ORDER` first, the rest as given."""
    first = [k for k in COMPILE_ORDER if k in kinds]
    return first + [k for k in kinds if k not in first]


def sources_fingerprint() -> str:
    """What numba's cached kernels depend on: interpreter, numba, machine and every source file
    of the estimators package (numba itself invalidates an entry when its file changes)."""
    import numba

    import estimators

    root = Path(estimators.__file__).parent
    digest = hashlib.sha256(f"{sys.version}|{numba.__version__}|{platform.machine()}".encode())
    for path in sorted(root.rglob("*.py")):
        st = path.stat()
        digest.update(f"{path.relative_to(root)}|{st.st_mtime_ns}|{st.st_size}\n".encode())
    return digest.hexdigest()


def stamp_dir() -> Path | None:
    """Where numba keeps the kernels' cache: ``NUMBA_CACHE_DIR``, else the kernels'
    ``__pycache__`` (None when it is not writable: then every start compiles in children)."""
    import numba

    import estimators.kernels

    cache_dir = getattr(numba.config, "CACHE_DIR", "")
    if cache_dir:
        path = Path(cache_dir)
    else:
        path = Path(estimators.kernels.__file__).parent / "__pycache__"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return path if os.access(path, os.W_OK) else None


def warm_kind(kind: str) -> None:
    """Compile (or load from numba's cache) the kernels of one estimator kind."""
    from estimators.registry import get_estimator

    get_estimator(kind).warm_up()


@contextlib.contextmanager
def compile_lock(kind: str) -> Iterator[None]:
    """Hold the kind's compile lock (waiting for another process that holds it); no lock when
    numba's cache directory is not writable."""
    where = stamp_dir()
    if where is None:
        yield
        return
    with open(where / f"fleethealth-kernels-{kind}.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes or the process dies
        yield


def _stamp_path(stamps: Path | None, kind: str) -> Path | None:
    return None if stamps is None else stamps / f"fleethealth-kernels-{kind}.stamp"


def is_cached(stamps: Path | None, kind: str, fingerprint: str | None) -> bool:
    """Whether numba's cache holds this kind, compiled from the sources of ``fingerprint``."""
    path = _stamp_path(stamps, kind)
    try:
        return path is not None and fingerprint is not None and path.read_text() == fingerprint
    except OSError:
        return False


def write_stamp(stamps: Path | None, kind: str, fingerprint: str | None) -> None:
    path = _stamp_path(stamps, kind)
    if path is None or fingerprint is None:
        return
    try:
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(fingerprint)
        tmp.replace(path)
    except OSError:
        log.warning("cannot write %s; the next start compiles %s again", path, kind)


class KernelWarmup:
    """Prepares each estimator kind's kernels in a background thread (see the module docstring).

    Args:
        kinds: estimator kind names to prepare.
        processes: child processes compiling at once; 0 compiles in the server's thread.
        enabled: False marks every kind ready at once (tests, or a process that never applies).
        on_ready: called with a kind's name once it is ready (or failed), from the warm-up thread.
        warm: compiles or loads one kind in this process (tests replace it).
        child_command: the command line of a child compiling ``kind`` (tests replace it).
    """

    def __init__(
        self,
        kinds: Sequence[str],
        *,
        processes: int,
        enabled: bool = True,
        on_ready: Callable[[str], None] | None = None,
        warm: Callable[[str], None] = warm_kind,
        child_command: Callable[[str], list[str]] | None = None,
    ) -> None:
        self.kinds = ordered_kinds(kinds)
        self.processes = processes
        self.enabled = enabled
        self.on_ready = on_ready
        self._warm = warm
        self._child_command = child_command or (
            lambda kind: [sys.executable, "-m", "app.kernels", "--exit-on-stdin-eof", kind]
        )
        self._status = {kind: KindStatus() for kind in self.kinds}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._children: dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]] = {}
        self._thread: threading.Thread | None = None
        self._fingerprint: str | None = None
        self._stamps: Path | None = None
        #: Set once every kind is ready or failed.
        self.done = threading.Event()

    # ------------------------------------------------------------------ reading
    def applicable_kinds(self) -> frozenset[str] | None:
        """Kinds whose streams may be applied now; None once every kind is done (no filter)."""
        if self.done.is_set():
            return None
        with self._lock:
            return frozenset(k for k, s in self._status.items() if s.state in ("ready", "failed"))

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """Kind -> ``{"status", "seconds"?, "error"?}`` for ``/readyz``."""
        now = time.monotonic()
        with self._lock:
            return {kind: status.public(now) for kind, status in self._status.items()}

    def all_ready(self) -> bool:
        with self._lock:
            return all(s.state == "ready" for s in self._status.values())

    # ------------------------------------------------------------------ running
    def start(self) -> None:
        if not self.enabled:
            now = time.monotonic()
            for kind in self.kinds:
                self._set(kind, "ready", started_s=now, finished_s=now)
            self.done.set()
            return
        target = self._run_children if self.processes > 0 else self._run_in_thread
        self._thread = threading.Thread(target=target, name="fleethealth-kernels", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Kill the compiling children and return within about ``timeout_s``: a compile running
        in the server's own thread (``processes == 0``) is left to die with the process."""
        self._stop.set()
        for proc, _ in list(self._children.values()):
            if proc.poll() is None:
                proc.kill()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _set(self, kind: str, state: KindState, **fields: Any) -> None:
        with self._lock:
            status = self._status[kind]
            status.state = state
            for name, value in fields.items():
                setattr(status, name, value)

    def _finish(self, kind: str, error: str | None = None) -> None:
        now = time.monotonic()
        self._set(kind, "failed" if error else "ready", finished_s=now, error=error)
        status = self._status[kind]
        seconds = now - (status.started_s or now)
        if error:
            log.error("kernels of %s failed after %.1f s: %s", kind, seconds, error)
        else:
            log.info("kernels of %s ready in %.1f s", kind, seconds)
        if self.on_ready is not None:
            try:
                self.on_ready(kind)
            except Exception:
                log.exception("on_ready(%s) failed", kind)

    def _load(self, kind: str) -> None:
        """Compile or load ``kind`` in this process and mark it ready or failed."""
        try:
            self._warm(kind)
        except Exception as exc:
            self._finish(kind, f"{type(exc).__name__}: {exc}")
            return
        write_stamp(self._stamps, kind, self._fingerprint)
        self._finish(kind)

    def _read_stamps(self) -> None:
        try:
            self._fingerprint = sources_fingerprint()
            self._stamps = stamp_dir()
        except Exception:
            log.exception("cannot tell whether numba's cache is warm; compiling every kind")

    def _cached(self, kind: str) -> bool:
        return is_cached(self._stamps, kind, self._fingerprint)

    def _run_in_thread(self) -> None:
        self._read_stamps()
        for kind in self.kinds:
            if self._stop.is_set():
                return
            self._set(kind, "compiling", started_s=time.monotonic())
            self._load(kind)
        self.done.set()

    def _run_children(self) -> None:
        self._read_stamps()
        queue = []
        for kind in self.kinds:
            if self._stop.is_set():
                return
            if self._cached(kind):
                self._set(kind, "loading", started_s=time.monotonic())
                self._load(kind)
            else:
                queue.append(kind)
        try:
            while (queue or self._children) and not self._stop.is_set():
                while queue and len(self._children) < self.processes:
                    kind = queue.pop(0)
                    if self._cached(kind):  # another process compiled it meanwhile
                        self._set(kind, "loading", started_s=time.monotonic())
                        self._load(kind)
                    else:
                        self._spawn(kind)
                finished = [(k, p, e) for k, (p, e) in self._children.items() if p.poll() is not None]
                if not finished:
                    self._stop.wait(POLL_S)
                    continue
                for kind, proc, err in finished:
                    del self._children[kind]
                    if self._stop.is_set():
                        break
                    self._collect(kind, proc, err)
        finally:
            for proc, err in self._children.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                err.close()
        if not self._stop.is_set():
            self.done.set()

    def _spawn(self, kind: str) -> None:
        self._set(kind, "compiling", started_s=time.monotonic())
        err = tempfile.TemporaryFile()  # noqa: SIM115 (closed in _collect or at stop)
        proc = subprocess.Popen(
            self._child_command(kind),
            stdin=subprocess.PIPE,  # closed when this process dies: the child then exits
            stdout=subprocess.DEVNULL,
            stderr=err,
            env=os.environ.copy(),
        )
        self._children[kind] = (proc, err)

    def _collect(self, kind: str, proc: subprocess.Popen[bytes], err: IO[bytes]) -> None:
        """A child ended: load the kind from the cache it filled, or compile it here if it failed."""
        if proc.stdin is not None:
            proc.stdin.close()
        err.seek(0)
        stderr = err.read().decode("utf-8", "replace").strip()
        err.close()
        if proc.returncode != 0:
            tail = stderr[-ERROR_TAIL_CHARS:] or f"exit code {proc.returncode}"
            log.warning("compiling %s in a child process failed (%s); compiling it here", kind, tail)
        self._set(kind, "loading")
        self._load(kind)


def _exit_when_parent_goes() -> None:
    """Exit at once when stdin closes (the server ended, however it ended). A raw read: a
    buffered reader's lock would still be held by this thread at interpreter shutdown."""
    while os.read(0, 4096):
        pass
    os._exit(3)


def main(argv: list[str] | None = None) -> int:
    """``python -m app.kernels [--exit-on-stdin-eof] KIND...``: compile the kinds' kernels into
    numba's cache, each under its compile lock, and stamp them (the server runs it with its end
    of the child's stdin kept open). A kind stamped by another process meanwhile is skipped."""
    kinds = sys.argv[1:] if argv is None else list(argv)
    if kinds[:1] == ["--exit-on-stdin-eof"]:
        kinds = kinds[1:]
        threading.Thread(target=_exit_when_parent_goes, daemon=True).start()
    fingerprint, stamps = sources_fingerprint(), stamp_dir()
    for kind in kinds:
        with compile_lock(kind):
            if not is_cached(stamps, kind, fingerprint):
                warm_kind(kind)
                write_stamp(stamps, kind, fingerprint)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
