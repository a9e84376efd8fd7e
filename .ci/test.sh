#!/usr/bin/env bash
# The README's test command: set up everything (virtual environment, pinned dependencies) and run the tests.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
source .ci/env.sh
# Two pytest workers (pytest-xdist), one torch thread each: both cores busy without oversubscription
# (SR_TEST_WORKERS=0 runs in one process).
workers="${SR_TEST_WORKERS:-2}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# tests/test_install.py fails (instead of skipping) unless the tests run under this clone's overlay.
export SR_TEST_OVERLAY="$venv"
"$venv/bin/ruff" check sr_imitation policies tests
if [ "$workers" = "0" ]; then
  exec "$venv/bin/python" -m pytest "$@"
fi
exec "$venv/bin/python" -m pytest -n "$workers" --dist loadgroup "$@"
