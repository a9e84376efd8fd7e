#!/usr/bin/env bash
# Issue 89 item 3: re-sleep a finished SR run's final stage with the anchor off (tools/experiments/resleep_final.sh's
# candidate anchor_off: sr-sleep, --sleep.anchor_strength=0, the run's other sleep settings and its final sleep's own
# seed, seed * 1000 + 10 k + 3, so that only the anchor differs from the run's sleep). Before 2026-12-07 16:00 UTC it
# passed the config's base --sleep.seed (0) instead: the re-sleeps of that day kept as
# sr_seed<S>_final_sleep_anchor_off_sampler0/.
#
#   bash tools/experiments/resleep_anchor_off.sh <run dir> <output dir>
#   e.g. bash tools/experiments/resleep_anchor_off.sh outputs/lerobot06_needle_m16/sr_0/sr_seed0 \
#        docs/results/lerobot06_needle_m16/sr_seed0_final_sleep_anchor_off
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/resleep_final.sh" "$1" "$2" anchor_off
