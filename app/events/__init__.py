"""The durable fleet event log: every fleet event with an id increasing per operator."""
