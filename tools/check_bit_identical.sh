#!/usr/bin/env bash
# Are two commits' tiny ACT-SR and SAC streams (two skills, a sleep after the second) bit-identical?
#
#   tools/check_bit_identical.sh BEFORE [AFTER]      # git refs; without AFTER, the working tree as it is
#
# Each side is exported (git archive, or the working tree's tracked and untracked files) to a scratch folder and
# runs tools/bit_identical_runs.py (this checkout's copy) there, with that side's code alone on PYTHONPATH (the
# editable installs' import hooks dropped), this clone's .venv (bash .ci/venv.sh) and one torch thread, the two
# sides at once, on the same recorded datasets (recorded first by BEFORE's code). Every *.safetensors file's sha256
# and every JSON file's (its stable keys: tools/bit_identical_runs.py) are listed in <scratch>/<side>/runs/sha256.txt
# and the two lists compared: exit 0 when equal, 1 with the differing lines. Runs at nice ${SR_BITCHECK_NICE:-19} (SR_BITCHECK_NICE=0 beside other work). SR_BITCHECK_DIR names
# the scratch folder (default: a new temporary one, kept).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
BEFORE="${1:?usage: tools/check_bit_identical.sh BEFORE [AFTER]}"
AFTER="${2:-}"
PY="$ROOT/.venv/bin/python"
[ -x "$PY" ] || { echo "no $PY: run bash .ci/venv.sh first" >&2; exit 2; }
SCRATCH="${SR_BITCHECK_DIR:-$(mktemp -d /tmp/sr_bitcheck.XXXXXX)}"
mkdir -p "$SCRATCH"

export_side() {  # $1 side name, $2 ref ('' = the working tree)
  local dir="$SCRATCH/$1"
  rm -rf "$dir" && mkdir -p "$dir/src"
  if [ -n "$2" ]; then
    git -C "$ROOT" archive "$(git -C "$ROOT" rev-parse "$2^{commit}")" | tar -x -C "$dir/src"
    git -C "$ROOT" rev-parse "$2^{commit}" > "$dir/ref.txt"
  else
    (cd "$ROOT" && git ls-files -co --exclude-standard -z | xargs -0 cp --parents -t "$dir/src")
    echo "working tree of $(git -C "$ROOT" rev-parse HEAD)" > "$dir/ref.txt"
  fi
}

in_side() {  # $1 side name, then the driver's arguments
  local dir="$SCRATCH/$1"
  shift
  (cd "$dir/src" && PYTHONPATH="$dir/src:$dir/src/policies/lerobot_policy_act_sr:$dir/src/policies/lerobot_env_sr" OMP_NUM_THREADS=1 \
     nice -n "${SR_BITCHECK_NICE:-19}" "$PY" "$ROOT/tools/bit_identical_runs.py" "$@")
}

export_side before "$BEFORE"
export_side after "$AFTER"
if [ ! -d "$SCRATCH/datasets" ]; then
  in_side before "$SCRATCH/datasets" > "$SCRATCH/datasets.log" 2>&1 \
    || { echo "recording the datasets failed; see $SCRATCH/datasets.log" >&2; exit 2; }
fi
pids=()
for side in before after; do
  in_side "$side" "$SCRATCH/datasets" "$SCRATCH/$side/runs" > "$SCRATCH/$side/log.txt" 2>&1 &
  pids+=("$!")
done
failed=0
for i in 0 1; do
  side=$([ "$i" = 0 ] && echo before || echo after)
  if ! wait "${pids[$i]}"; then
    echo "$side: the runs failed; see $SCRATCH/$side/log.txt" >&2
    tail -20 "$SCRATCH/$side/log.txt" >&2
    failed=1
  fi
done
[ "$failed" = 0 ] || exit 2
for side in before after; do
  echo "$side ($(cat "$SCRATCH/$side/ref.txt")): $(wc -l < "$SCRATCH/$side/runs/sha256.txt") files," \
       "code from $(cat "$SCRATCH/$side/runs/source.txt")"
done
if diff "$SCRATCH/before/runs/sha256.txt" "$SCRATCH/after/runs/sha256.txt"; then
  echo "bit-identical: every checkpoint and results file equal ($SCRATCH)"
else
  echo "DIFFERENT (lines above; runs in $SCRATCH)"
  exit 1
fi
