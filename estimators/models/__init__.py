"""Reference plant models shipped with the estimators (linearized, discrete, JSON-ready)."""
