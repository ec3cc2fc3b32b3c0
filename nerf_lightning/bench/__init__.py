"""Benchmarks: the runner (``nerf-bench``), its suites and results table, and what the micro-benchmarks share."""
