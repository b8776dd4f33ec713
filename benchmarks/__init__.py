"""Benchmarks: each ``bench_*.py`` has ``run() -> dict``; ``make bench`` prints them as JSON."""
