"""Benchmarks: ``python -m bench.run`` (table + JSON) and ``pytest bench/`` (pytest-benchmark)."""
