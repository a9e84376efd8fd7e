"""Moved (issue 61): the grid benchmark times the experiment runner, so it lives with it:
``python -m sr_imitation.experiments.grid_benchmark``. Running the old name says so in one line."""

raise SystemExit("sr_imitation.benchmarks.grid moved: python -m sr_imitation.experiments.grid_benchmark")
