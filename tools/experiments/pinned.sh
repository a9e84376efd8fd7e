#!/usr/bin/env bash
# Run a long experiment from a pinned commit, so that its results.json names a clean commit however the checkout
# moves on while it runs (the grid runner imports the package once; lazily imported modules would otherwise come
# from whatever the checkout holds later).
#
#   bash tools/experiments/pinned.sh <commit> <log file> <command...>
#
# Creates (once) a git worktree of <commit> beside the clone (<clone>/../wt-<short commit>), links the clone's
# datasets/ folders into it (datasets are identified by content, not path), and runs <command> there in the
# background with this clone's .venv, the worktree's code first on PYTHONPATH and one torch thread. Relative paths
# in <command> resolve in the worktree: give output_root and archive as absolute paths into the clone.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
# shellcheck source=tools/experiments/worktree.sh
source "$root/tools/experiments/worktree.sh"
log="$2"
wt="$(pinned_worktree "$root" "$1")"
shift 2
cd "$wt"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
export PYTHONPATH="$wt:$wt/policies/lerobot_policy_act_sr:$wt/policies/lerobot_env_sr${PYTHONPATH:+:$PYTHONPATH}"
nohup setsid "$root/.venv/bin/python" "$@" > "$log" 2>&1 &
echo "started in $wt (pid $!), log $log"
