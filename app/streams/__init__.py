"""Admin operations on a stream: rewinding it past batches that should never have been logged."""
