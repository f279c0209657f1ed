"""Health indicators, per-sample outputs, estimator events and remaining useful life."""
