#!/usr/bin/env bash
# The README's test command: set up everything (virtual environment, pinned dependencies) and run the tests.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
source .ci/env.sh
# Two pytest workers (pytest-xdist), one torch thread each: both cores busy without oversubscription
# (SR_TEST_WORKERS=0 runs in one process). Each test file runs on one worker (--dist loadfile): a module's shared
# fixtures (recorded datasets, tiny trained runs, the grid's Ray) are built once, and the Ray tests never run beside
# each other. (--dist loadgroup's xdist_group marks do nothing under pytest 9 with xdist 3.8: tests/test_ci_dist.py.)
# Two tiers: without --all, the tests marked `slow` (the multi-process end-to-end routes: stock lerobot-train /
# lerobot-eval subprocesses, torchrun, pip installs, the kill -9 harness, two writers at once, the grid on Ray, the
# recipe copy) are left out; every unit-level check of the same code stays. `--all` runs both tiers (CI: .ci/run).
tier=(-m "not slow")
args=()
for arg in "$@"; do
  if [ "$arg" = "--all" ]; then tier=(); else args+=("$arg"); fi
done
set -- "${args[@]+"${args[@]}"}"
workers="${SR_TEST_WORKERS:-2}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# Temporary files (pytest's tmp_path and every tempfile of the tests and of the processes they start) on a RAM disk
# where the machine has one with room. On this project's VMs (ext4 mounted with discard) an unlink costs 3.4 ms, so
# deleting an earlier full session's folder (23 000 files) stalled the next small pytest session for 70-90 s; on
# /dev/shm it takes about a second (the whole suite's own time did not change measurably; docs/BENCHMARKS.md). Passed
# tests' folders are removed at the session's end (pyproject.toml), so little RAM stays in use after it.
# SR_TEST_TMPDIR=<folder> puts them elsewhere; SR_TEST_TMPDIR= (empty) leaves TMPDIR as it is.
tmp="${SR_TEST_TMPDIR-/dev/shm/sr_tests}"
if [ -n "$tmp" ] && mkdir -p "$tmp" 2>/dev/null && [ -w "$tmp" ] \
    && [ "$(df --output=avail -k "$tmp" 2>/dev/null | tail -n 1)" -ge 4000000 ] 2>/dev/null; then
  export TMPDIR="$tmp"
fi
# tests/test_install.py fails (instead of skipping) unless the tests run under this clone's overlay.
export SR_TEST_OVERLAY="$venv"
"$venv/bin/ruff" check sr_imitation policies tests experiments
# This clone's code byte-compiled once, before the tests: every process they start (lerobot-train, torchrun ranks, Ray
# workers, the sr-* commands) compiles it again where PYTHONDONTWRITEBYTECODE is set (0.6-0.9 s a process here).
"$venv/bin/python" -m compileall -q -j 0 sr_imitation policies tests experiments >/dev/null
if [ "$workers" = "0" ]; then
  exec "$venv/bin/python" -m pytest "${tier[@]+"${tier[@]}"}" "$@"
fi
exec "$venv/bin/python" -m pytest -n "$workers" --dist loadfile --no-loadscope-reorder "${tier[@]+"${tier[@]}"}" "$@"
