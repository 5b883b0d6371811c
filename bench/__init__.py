"""Benchmarks and probes of the shells renderer, each run as ``python -m bench.NAME``."""
