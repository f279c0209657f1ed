"""Service settings, read from ``FLEETHEALTH_*`` environment variables."""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """All settings of the service; see docs/operations.md for each one."""

    model_config = SettingsConfigDict(env_prefix="FLEETHEALTH_", extra="ignore")

    database_url: str = "sqlite:///./data/fleethealth.db"
    host: str = "127.0.0.1"
    port: int = 8000
    bootstrap_admin_key: str | None = None
    bootstrap_operator: str = "default"
    max_body_bytes: int = Field(default=256 * 1024 * 1024, gt=0)
    max_batch_samples: int = Field(default=5_000_000, gt=0)
    # Upper bound of the bytes one batch may decode to (an Arrow body's decompressed buffers);
    # the bound applied is the smaller of this and max_batch_samples x (channels + 1) x 9 bytes.
    max_batch_decoded_bytes: int = Field(default=1024 * 1024 * 1024, gt=0)
    # Memory all batch requests of the process may hold at once (bodies in memory, decoding, log
    # encoding); a request that cannot have its share within ingest_memory_wait_s gets 503.
    ingest_memory_bytes: int = Field(default=2 * 1024 * 1024 * 1024, gt=0)
    ingest_memory_wait_s: float = Field(default=30.0, ge=0)
    # Bodies above this are spooled to a temporary file as they arrive (TMPDIR), not held in memory.
    body_spool_bytes: int = Field(default=8 * 1024 * 1024, ge=0)
    max_wait_s: float = Field(default=60.0, ge=0)
    # Input bounds on every batch and frame (app/telemetry/validation.py, docs/operations.md).
    max_abs_value: float = Field(default=1e12, gt=0, le=2**53)
    max_time_s: float = Field(default=1e10, gt=0)
    max_future_s: float = Field(default=86_400.0, ge=0)
    sqlite_synchronous: Literal["FULL", "NORMAL"] = "FULL"
    processor_enabled: bool = True
    # SQLite file: "on" runs the processor in a child process of serve (its own interpreter
    # lock; app/processing/apply_process.py, docs/scaling.md); "off" in a thread of serve.
    apply_process: Literal["on", "off"] = "on"
    processor_scan_interval_s: float = Field(default=2.0, gt=0)
    processor_max_samples_per_txn: int = Field(default=1_000_000, gt=0)
    processor_max_batches_per_txn: int = Field(default=256, gt=0)
    # Group commit of applies: streams applied in one transaction (each in its own savepoint).
    processor_max_streams_per_txn: int = Field(default=64, gt=0)
    # ... and no more streams join an apply transaction once it has run this long (SQLite: one
    # that runs inside the write lock, which acknowledgements wait for; PostgreSQL: one of small
    # applies, under the streams' row locks).
    processor_txn_budget_s: float = Field(default=0.005, gt=0)
    # The same bound for a SQLite group computed outside the write lock (a read transaction,
    # then a write transaction that only stores) and for a PostgreSQL group of large applies
    # (Processor._bound_s). A longer group spreads its fixed cost (its transactions, the reads
    # of its streams' rows) over more streams when many streams apply at once; its streams'
    # results wait for its commit.
    processor_compute_budget_s: float = Field(default=0.05, gt=0)
    # Group commit of the telemetry log: appends committed in one transaction at most.
    log_writer_max_group: int = Field(default=256, gt=0)
    # PostgreSQL: wake-ups, applied marks and fleet events cross processes by LISTEN/NOTIFY
    # (needed when workers apply in other processes; "off" keeps them in this process).
    pg_notify: Literal["on", "off"] = "on"
    # A stream whose apply raises is retried after processor_retry_backoff_s, doubling per
    # attempt up to processor_retry_backoff_max_s; after processor_max_attempts it is failed.
    processor_max_attempts: int = Field(default=5, gt=0)
    processor_retry_backoff_s: float = Field(default=1.0, gt=0)
    processor_retry_backoff_max_s: float = Field(default=60.0, gt=0)
    store_sample_outputs: bool = True
    log_retention_s: float | None = Field(default=None, gt=0)
    # Deleted aircraft and actuators keep their data this long, then the processor's periodic
    # scan purges them (default 30 days).
    deleted_retention_s: float = Field(default=30 * 86_400.0, gt=0)
    # Per-sample outputs kept per stream, in seconds of stream time before its last applied
    # sample (None keeps them all; health windows, events and RUL are always kept).
    sample_output_retention_s: float | None = Field(default=None, gt=0)
    warm_kernels: bool = True
    # Child processes compiling estimator kinds at once into numba's cache at start-up; 0
    # compiles inside the server (app/kernels.py, docs/operations.md "Start-up").
    warm_kernels_processes: int = Field(default=2, ge=0)
    # WebSocket streaming (docs/api.md, "Streaming").
    ws_max_frame_bytes: int = Field(default=16 * 1024 * 1024, gt=0)
    ws_max_inflight: int = Field(default=16, gt=0)
    # Frames read ahead per connection (logged in order as the window frees) and process-wide;
    # past ws_slow_down_frames waiting (queued + in flight) a connection is told to slow down.
    ws_max_queued_frames: int = Field(default=64, gt=0)
    ws_max_queued_bytes: int = Field(default=64 * 1024 * 1024, gt=0)
    ws_max_queued_frames_total: int = Field(default=8192, gt=0)
    ws_max_queued_bytes_total: int = Field(default=512 * 1024 * 1024, gt=0)
    ws_slow_down_frames: int = Field(default=32, gt=1)
    ws_subscriber_queue: int = Field(default=1000, gt=0)
    ws_auth_timeout_s: float = Field(default=10.0, gt=0)
    ws_close_timeout_s: float = Field(default=10.0, gt=0)
    # Keepalive pings on every WebSocket (uvicorn's own defaults): a peer that answers no ping
    # within the timeout is dropped.
    ws_ping_interval_s: float = Field(default=20.0, gt=0)
    ws_ping_timeout_s: float = Field(default=20.0, gt=0)
    # permessage-deflate on WebSockets, when a client offers it. Off by default: telemetry
    # frames (Arrow, float64) barely compress, and deflating every small ack and result costs
    # more CPU than it saves bytes on a LAN (docs/benchmarks.md, "WebSocket streaming").
    ws_per_message_deflate: bool = False
    # How often the process looks, in one query for all its stream connections, for results in
    # the store that never reached their connection (a wake-up from another process lost).
    ws_result_poll_s: float = Field(default=1.0, gt=0)
    # How often an open WebSocket's key is re-read (once per key and scope for every connection
    # of the process): a revoked key or a lost scope closes the connection (1008) within this
    # time, whichever process revoked it.
    ws_auth_recheck_s: float = Field(default=5.0, gt=0)
    # A valid API key is remembered this long, so most requests read no key from the database:
    # a key revoked or re-scoped by another process keeps working (with its old scopes) for at
    # most this time. 0 reads the key on every request.
    auth_cache_ttl_s: float = Field(default=5.0, ge=0)
    # The actuator a telemetry path names (its primary key and channels), remembered this long
    # per operator; the log writer re-checks every append against the locked actuator row, so a
    # deletion is honoured at once whichever process made it. 0 turns it off.
    actuator_cache_ttl_s: float = Field(default=30.0, ge=0)
    # Entries of each of those two caches (the oldest makes room).
    lookup_cache_entries: int = Field(default=10_000, gt=0)
    socket_send_buffer_bytes: int | None = Field(default=None, gt=0)
    shutdown_timeout_s: float = Field(default=10.0, gt=0)
    # Fleet event subscribers re-read the log this often (events applied by other processes).
    events_poll_s: float = Field(default=1.0, gt=0)
    # Webhooks (docs/operations.md, "Webhooks"): the deliverer thread polls the outbox every
    # webhook_poll_s, sends up to webhook_batch rows a round with webhook_timeout_s per request,
    # retries after webhook_retry_base_s doubling per attempt up to webhook_retry_max_s, and
    # gives up after webhook_max_attempts.
    webhooks_enabled: bool = True
    webhook_poll_s: float = Field(default=1.0, gt=0)
    webhook_batch: int = Field(default=16, gt=0)
    webhook_timeout_s: float = Field(default=10.0, gt=0)
    webhook_max_attempts: int = Field(default=12, gt=0)
    webhook_retry_base_s: float = Field(default=5.0, gt=0)
    webhook_retry_max_s: float = Field(default=3600.0, gt=0)
    # /metrics: "key" needs a key with the read scope, "open" needs none, "off" answers 404.
    metrics_access: Literal["off", "key", "open"] = "key"
    # Retry-After (seconds) of a 503 when the database is unreachable or out of space.
    storage_retry_after_s: int = Field(default=5, gt=0)
    # /readyz is not ready while the file system of a SQLite database has less free space.
    storage_min_free_bytes: int = Field(default=64 * 1024 * 1024, ge=0)

    @field_validator("bootstrap_admin_key")
    @classmethod
    def _key_not_placeholder(cls, v: str | None) -> str | None:
        if v is not None and (len(v) < 16 or v.lower() in {"changeme", "change-me", "secret"}):
            raise ValueError("FLEETHEALTH_BOOTSTRAP_ADMIN_KEY must be at least 16 characters")
        return v


@lru_cache
def get_settings() -> Settings:
    return Settings()
