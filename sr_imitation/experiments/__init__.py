"""Experiments that produce the numbers in docs/RESULTS.md (each a module with its own command)."""
