"""Benchmark scenarios and harnesses (kept apart from tests; results go to docs/benchmarks.md)."""
