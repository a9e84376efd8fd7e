#!/usr/bin/env bash
# The README's test command: set up everything (virtual environment, pinned dependencies) and run the tests.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
source .ci/env.sh
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
"$venv/bin/ruff" check sr_imitation policies tests
exec "$venv/bin/python" -m pytest "$@"
