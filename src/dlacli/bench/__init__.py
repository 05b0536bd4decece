"""Benchmarks: metrics, suites, charts."""
