"""Benchmark scripts (``python -m sr_imitation.benchmarks.<name>``); they print their results."""
