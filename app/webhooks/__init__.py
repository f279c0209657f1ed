"""Webhooks: per-operator subscriptions to the fleet event log, delivered through a durable
outbox with signatures, retries and a delivery log."""
