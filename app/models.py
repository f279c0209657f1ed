"""Every ORM table. Times of samples are stream seconds (float); wall-clock times are UTC
datetimes stored with time zone and normalized on read (SQLite returns naive ones)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    false,
    text,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from app.db import Base


class UTCDateTime(TypeDecorator[datetime]):
    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetime")
        return value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value


def utcnow() -> datetime:
    return datetime.now(UTC)


class Operator(Base):
    __tablename__ = "operators"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class ApiKey(Base):
    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(100), default="")
    prefix: Mapped[str] = mapped_column(String(16))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    scopes: Mapped[str] = mapped_column(String(100))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    operator: Mapped[Operator] = relationship(lazy="raise")


class Aircraft(Base):
    __tablename__ = "aircraft"
    __table_args__ = (UniqueConstraint("operator_id", "tail"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    tail: Mapped[str] = mapped_column(String(32))
    description: Mapped[str | None] = mapped_column(String(500), nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # Soft deletion: hidden from reads and ingest, purged after FLEETHEALTH_DELETED_RETENTION_S.
    deleted_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    actuators: Mapped[list[Actuator]] = relationship(back_populates="aircraft", lazy="raise")


class Actuator(Base):
    """An actuator and its telemetry stream (one stream per actuator)."""

    __tablename__ = "actuators"
    __table_args__ = (UniqueConstraint("aircraft_id", "actuator_id"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    aircraft_id: Mapped[int] = mapped_column(ForeignKey("aircraft.id", ondelete="CASCADE"))
    actuator_id: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(32))
    channels: Mapped[list[str]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # What the telemetry log holds; written by ingest under a lock on this row.
    last_logged_seq: Mapped[int] = mapped_column(BigInteger, default=0)
    last_logged_t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    # The highest client sequence number of a streamed frame logged (WebSocket resume).
    last_client_seq: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    # Soft deletion (see Aircraft.deleted_at).
    deleted_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    aircraft: Mapped[Aircraft] = relationship(back_populates="actuators", lazy="raise")
    stream: Mapped[Stream] = relationship(lazy="raise", uselist=False)


class Stream(Base):
    """What the estimators have applied; written by the processor under a lock on this row
    (a separate row from the actuator's, so ingest never waits for an apply)."""

    __tablename__ = "streams"
    actuator_pk: Mapped[int] = mapped_column(
        ForeignKey("actuators.id", ondelete="CASCADE"), primary_key=True
    )
    last_applied_seq: Mapped[int] = mapped_column(BigInteger, default=0)
    last_applied_t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    # A new stream has nothing to vouch for: learning until its estimators report.
    status: Mapped[str] = mapped_column(String(8), default="learning")
    # Why the stream is no longer applied (status failed); None while it is.
    failure: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # The latest RUL prognosis of any estimator (the smallest 5 % quantile), for the fleet board.
    rul_t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    rul_q05_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    rul_q50_s: Mapped[float | None] = mapped_column(Float, nullable=True)


class EstimatorState(Base):
    """An estimator attached to an actuator: its config and its latest committed state."""

    __tablename__ = "estimator_states"
    actuator_pk: Mapped[int] = mapped_column(
        ForeignKey("actuators.id", ondelete="CASCADE"), primary_key=True
    )
    estimator: Mapped[str] = mapped_column(String(32), primary_key=True)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)
    applied_seq: Mapped[int] = mapped_column(BigInteger, default=0)
    status: Mapped[str] = mapped_column(String(8), default="learning")
    reasons: Mapped[list[str]] = mapped_column(JSON, default=list)
    # The estimator's latest diagnostic picture (fault isolation), replaced on each batch.
    diagnosis_t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    diagnosis: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    # The config version in effect (estimator_config_versions) and the baseline (epoch of the
    # physical part: a repair or replacement starts a new one) the state belongs to.
    config_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    baseline: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    # A maintenance action recorded while batches of the old part were still pending: the
    # estimator restarts from its initial state, as baseline reset_baseline, at batch
    # reset_at_seq (the first one logged after the action).
    reset_at_seq: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    reset_baseline: Mapped[int | None] = mapped_column(Integer, nullable=True)


class TelemetryBatch(Base):
    """The telemetry log: one row per accepted batch, in stream order (seq)."""

    __tablename__ = "telemetry_batches"
    __table_args__ = (
        UniqueConstraint("actuator_pk", "seq"),
        UniqueConstraint("actuator_pk", "batch_id"),
    )
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(BigInteger)
    batch_id: Mapped[str] = mapped_column(String(128))
    content_hash: Mapped[str] = mapped_column(String(32))
    n_samples: Mapped[int] = mapped_column(Integer)
    t_first_s: Mapped[float] = mapped_column(Float)
    t_last_s: Mapped[float] = mapped_column(Float)
    received_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # Applied when seq <= its stream's last_applied_seq (no per-batch stamp: on SQLite an update of
    # the row rewrites its whole payload).
    # The client closed the run after this batch (part of the batch's identity).
    end_of_run: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    payload: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)


class HealthWindowRow(Base):
    __tablename__ = "health_windows"
    __table_args__ = (Index("ix_health_windows_stream_time", "actuator_pk", "estimator", "t_end_s"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    estimator: Mapped[str] = mapped_column(String(32))
    seq: Mapped[int] = mapped_column(BigInteger)
    # Which config version and baseline produced the row.
    config_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    baseline: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    t_start_s: Mapped[float] = mapped_column(Float)
    t_end_s: Mapped[float] = mapped_column(Float)
    n_samples: Mapped[int] = mapped_column(Integer)
    indicators: Mapped[dict[str, Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(8))
    reasons: Mapped[list[str]] = mapped_column(JSON)


class SampleOutputRow(Base):
    """Per-sample estimator outputs of one applied batch, as a compressed Arrow IPC blob."""

    __tablename__ = "sample_outputs"
    __table_args__ = (Index("ix_sample_outputs_stream_time", "actuator_pk", "estimator", "t_last_s"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    estimator: Mapped[str] = mapped_column(String(32))
    seq: Mapped[int] = mapped_column(BigInteger)
    # Which config version and baseline produced the row.
    config_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    baseline: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    t_first_s: Mapped[float] = mapped_column(Float)
    t_last_s: Mapped[float] = mapped_column(Float)
    n_samples: Mapped[int] = mapped_column(Integer)
    payload: Mapped[bytes] = mapped_column(LargeBinary)


class EstimatorEventRow(Base):
    __tablename__ = "estimator_events"
    __table_args__ = (Index("ix_estimator_events_stream_time", "actuator_pk", "t_s"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    estimator: Mapped[str] = mapped_column(String(32))
    seq: Mapped[int] = mapped_column(BigInteger)
    # Which config version and baseline produced the row.
    config_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    baseline: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    t_s: Mapped[float] = mapped_column(Float)
    kind: Mapped[str] = mapped_column(String(48))
    detail: Mapped[dict[str, Any]] = mapped_column(JSON)


class RulEstimateRow(Base):
    """One remaining-useful-life prognosis; times are seconds of stream time."""

    __tablename__ = "rul_estimates"
    __table_args__ = (Index("ix_rul_estimates_stream_time", "actuator_pk", "estimator", "t_s"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    estimator: Mapped[str] = mapped_column(String(32))
    seq: Mapped[int] = mapped_column(BigInteger)
    # Which config version and baseline produced the row.
    config_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    baseline: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    t_s: Mapped[float] = mapped_column(Float)
    mean_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    std_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    q05_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    q50_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    q95_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    optimistic_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    pessimistic_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    threshold: Mapped[float] = mapped_column(Float)
    health: Mapped[dict[str, Any]] = mapped_column(JSON)
    assumption: Mapped[dict[str, Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(8))
    reasons: Mapped[list[str]] = mapped_column(JSON)


class EstimatorConfigVersion(Base):
    """Every configuration an estimator of an actuator has had, from the batch it applies to."""

    __tablename__ = "estimator_config_versions"
    __table_args__ = (UniqueConstraint("actuator_pk", "estimator", "version"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    estimator: Mapped[str] = mapped_column(String(32))
    version: Mapped[int] = mapped_column(Integer)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    # The first batch (stream seq) applied with this version.
    from_seq: Mapped[int] = mapped_column(BigInteger)
    # "kept": the estimator carried its state on; "reset": it restarted from its initial state.
    state: Mapped[str] = mapped_column(String(8), default="kept")
    comment: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    created_by_key_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


class MaintenanceAction(Base):
    """An inspection, repair or replacement of an actuator; a repair or replacement starts a
    new baseline from batch ``from_seq``."""

    __tablename__ = "maintenance_actions"
    __table_args__ = (Index("ix_maintenance_actions_actuator", "actuator_pk", "id"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    action: Mapped[str] = mapped_column(String(16))
    performed_by: Mapped[str] = mapped_column(String(200))
    performed_at: Mapped[datetime] = mapped_column(UTCDateTime)
    comment: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    # The baseline in force after the action, and the first batch it covers (None: inspection).
    baseline: Mapped[int] = mapped_column(Integer)
    from_seq: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    status_before: Mapped[str] = mapped_column(String(8))
    recorded_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    recorded_by_key_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


# ----------------------------------------------------------------------------- event log
class EventCounter(Base):
    """The last fleet event id given out per operator. Its row is locked by the transaction
    that appends events, so ids are given in commit order: a reader that has seen id n never
    later sees a smaller id appear (no event lost behind a cursor)."""

    __tablename__ = "event_counters"
    operator_id: Mapped[int] = mapped_column(
        ForeignKey("operators.id", ondelete="CASCADE"), primary_key=True
    )
    last_event_id: Mapped[int] = mapped_column(BigInteger, default=0)


class FleetEventRow(Base):
    """The durable fleet event log: one row per event, ``event_id`` increasing per operator."""

    __tablename__ = "fleet_events"
    __table_args__ = (
        UniqueConstraint("operator_id", "event_id"),
        Index("ix_fleet_events_operator_type", "operator_id", "type", "event_id"),
    )
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    event_id: Mapped[int] = mapped_column(BigInteger)
    type: Mapped[str] = mapped_column(String(48))
    # The actuator's names as they were when the event happened (an actuator removed later
    # leaves its events readable).
    tail: Mapped[str] = mapped_column(String(32))
    actuator_id: Mapped[str] = mapped_column(String(64))
    actuator_pk: Mapped[int | None] = mapped_column(
        ForeignKey("actuators.id", ondelete="SET NULL"), nullable=True
    )
    seq: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    body: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


# ----------------------------------------------------------------------------- alarms
class AlarmRow(Base):
    """An alarm: raised by a rule from a logged event, then acknowledged and cleared.

    At most one alarm per (actuator, cause, subject) is open (status other than cleared): a
    partial unique index holds it.
    """

    __tablename__ = "alarms"
    __table_args__ = (
        Index(
            "uq_alarms_open_cause",
            "actuator_pk",
            "cause",
            "subject",
            unique=True,
            sqlite_where=text("status != 'cleared'"),
            postgresql_where=text("status != 'cleared'"),
        ),
        Index("ix_alarms_operator_status", "operator_id", "status", "id"),
    )
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"))
    cause: Mapped[str] = mapped_column(String(16))
    subject: Mapped[str] = mapped_column(String(128), default="")
    estimator: Mapped[str | None] = mapped_column(String(32), nullable=True)
    severity: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16), default="active")
    message: Mapped[str] = mapped_column(String(500))
    # The event that raised it, and the latest that re-triggered or changed it.
    raised_event_id: Mapped[int] = mapped_column(BigInteger)
    last_event_id: Mapped[int] = mapped_column(BigInteger)
    occurrences: Mapped[int] = mapped_column(Integer, default=1)
    detail: Mapped[dict[str, Any]] = mapped_column(JSON)
    raised_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    raised_t_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    acknowledged_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    acknowledged_by: Mapped[str | None] = mapped_column(String(200), nullable=True)
    acknowledge_comment: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    cleared_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    cleared_by: Mapped[str | None] = mapped_column(String(200), nullable=True)
    clear_comment: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    cleared_event_id: Mapped[int | None] = mapped_column(BigInteger, nullable=True)


# ----------------------------------------------------------------------------- webhooks
class WebhookTarget(Base):
    """Where an operator's webhooks may deliver: a URL prefix registered by the service's
    administrator (``fleethealth webhooks allow``)."""

    __tablename__ = "webhook_targets"
    __table_args__ = (UniqueConstraint("operator_id", "prefix"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    prefix: Mapped[str] = mapped_column(String(2000))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class WebhookSubscription(Base):
    __tablename__ = "webhook_subscriptions"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    url: Mapped[str] = mapped_column(String(2000))
    # Event types delivered (empty: every logged type) and tails (None: every tail).
    event_types: Mapped[list[str]] = mapped_column(JSON)
    tails: Mapped[list[str] | None] = mapped_column(JSON, nullable=True)
    # The signing key, kept to sign each delivery (shown once, at creation).
    secret: Mapped[str] = mapped_column(String(200))
    description: Mapped[str | None] = mapped_column(String(500), nullable=True)
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class WebhookDelivery(Base):
    """The durable outbox: one row per (subscription, event), retried until delivered or
    out of attempts. The body is stored so that every attempt sends the same bytes."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (
        Index("ix_webhook_deliveries_due", "status", "next_attempt_at"),
        Index("ix_webhook_deliveries_subscription", "subscription_id", "id"),
    )
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    subscription_id: Mapped[int] = mapped_column(
        ForeignKey("webhook_subscriptions.id", ondelete="CASCADE")
    )
    operator_id: Mapped[int] = mapped_column(ForeignKey("operators.id", ondelete="CASCADE"))
    event_id: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    event_type: Mapped[str] = mapped_column(String(48))
    idempotency_key: Mapped[str] = mapped_column(String(64), unique=True)
    body: Mapped[str] = mapped_column(Text)
    status: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    last_attempt_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    last_status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    last_error: Mapped[str | None] = mapped_column(String(500), nullable=True)
    delivered_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class WebhookAttempt(Base):
    """One try of a delivery, for the delivery log."""

    __tablename__ = "webhook_attempts"
    __table_args__ = (Index("ix_webhook_attempts_delivery", "delivery_id", "attempt"),)
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    delivery_id: Mapped[int] = mapped_column(
        ForeignKey("webhook_deliveries.id", ondelete="CASCADE")
    )
    attempt: Mapped[int] = mapped_column(Integer)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    error: Mapped[str | None] = mapped_column(String(500), nullable=True)
    duration_ms: Mapped[float] = mapped_column(Float)


class StreamRewind(Base):
    """An admin rewind of a stream: who, when, why, and every batch it discarded (the record
    stays when the batches are gone)."""

    __tablename__ = "stream_rewinds"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    actuator_pk: Mapped[int] = mapped_column(ForeignKey("actuators.id", ondelete="CASCADE"), index=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # "api key <id>" or "cli <user>@<host>"; key_id when it came through the API.
    actor: Mapped[str] = mapped_column(String(200))
    key_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    reason: Mapped[str] = mapped_column(String(500))
    to_seq: Mapped[int] = mapped_column(BigInteger)
    from_logged_seq: Mapped[int] = mapped_column(BigInteger)
    from_applied_seq: Mapped[int] = mapped_column(BigInteger)
    # The estimators had applied a discarded batch: they restart and re-apply 1..to_seq.
    estimators_reset: Mapped[bool] = mapped_column(Boolean)
    # [{"seq", "batch_id", "n_samples", "t_first_s", "t_last_s", "received_at"}, ...]
    discarded: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
