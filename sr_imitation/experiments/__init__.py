"""The reusable experiment drivers (the grid and the comparisons it runs, archives, hypothesis tests, the kill -9
harness, sleep replays), each a module with its own command; one protocol's analyses of docs/RESULTS.md live in the
repository's ``experiments/``, which is not installed."""
