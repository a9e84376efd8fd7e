"""Simulated environments of sr_imitation."""
