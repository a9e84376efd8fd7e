#!/usr/bin/env bash
# The README's main job: set up the environment (as the test command does), then show what sleep buys: SR beside
# wake-only on the small-memory needle preset (configs/needle_cpu_m16.json), both runs at once (one process and one
# torch thread each), then outputs/needle_main/comparison.png and results.md
# (sr_imitation/experiments/main_compare.py). Extra arguments go to that job, e.g.
#   bash .ci/main.sh --train.resume=true          # continue an interrupted job (a finished run is skipped)
#   bash .ci/main.sh --train.seed=1001            # another training seed
# With --config_path the single-run job of earlier versions runs instead (sr-main: record, one stream, report):
#   bash .ci/main.sh --config_path=configs/needle_cpu.json
#   bash .ci/main.sh --config_path=configs/needle_paper.json
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
source .ci/env.sh
for arg in "$@"; do
  case "$arg" in --config_path=*) exec "$venv/bin/sr-main" "$@" ;; esac
done
exec "$venv/bin/python" -m sr_imitation.experiments.main_compare "$@"
