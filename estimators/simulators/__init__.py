"""Reference plants with ground truth, for tests, benchmarks and the demo fleet."""
