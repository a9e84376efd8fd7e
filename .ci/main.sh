#!/usr/bin/env bash
# The README's main-job command: set up the environment (as the test command does), then run the main job on
# the embedded CPU preset: record expert demos, run the five-skill wake-sleep stream with evaluation after
# every phase, and write tables, plots and videos. Extra arguments go to sr-main, e.g.
#   bash .ci/main.sh --config_path=configs/needle_paper.json
#   bash .ci/main.sh --train.resume=true          # continue a run that was interrupted
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
source .ci/env.sh
has_config=false
for arg in "$@"; do case "$arg" in --config_path=*) has_config=true ;; esac; done
if [ "$has_config" = true ]; then
  exec "$venv/bin/sr-main" "$@"
fi
exec "$venv/bin/sr-main" --config_path=configs/needle_cpu.json "$@"
