"""The telemetry log: durable, idempotent, ordered append of batches (REST and WebSocket)."""
