#!/usr/bin/env bash
# Archive every queue run that ended with status 0 and is not committed yet, then drop its line from the pending file.
# For each "<name> rc=0" of outputs/queue.txt.done, its line in outputs/queue.txt.taken gives --archive=<dir>,
# --variants=[<variant>] and --seeds=[<seed>]; <dir>/<variant>_seed<seed> (the driver's --archive copied it there)
# is committed with the queue's record of it by queue_archive.sh, the message naming the line's commit and the CPU of
# its start line; then every archived line leaves tools/experiments/queue_pending.txt (one commit). A run whose
# archived folder is missing, or whose line names no archive, is named and left alone. Never during a full test run
# (tests/infra/test_provenance.py fails when HEAD moves under it). SR runs of a protocol that re-sleeps them still need
# tools/experiments/resleep_archived.sh while their outputs exist (the pending file's header says which).
#
#   bash tools/experiments/queue_archive_done.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
queue="outputs/queue.txt"; pending="tools/experiments/queue_pending.txt"
say() { echo "queue_archive_done: $*" >&2; }
[ -f "$queue.done" ] || { say "$queue.done: no run has ended"; exit 0; }
archived=()
for name in $(grep -o ' [A-Za-z0-9_.-]* rc=0$' "$queue.done" | awk '{print $1}' | sort -u); do
  line="$(grep -m1 "^$name " "$queue.taken" 2>/dev/null || true)"
  [ -n "$line" ] || continue
  archive="$(grep -o -- '--archive=[^ ]*' <<< "$line" | head -n 1 | cut -d= -f2- || true)"
  variant="$(grep -o -- '--variants=\[[A-Za-z0-9_]*\]' <<< "$line" | head -n 1 | sed 's/.*\[\(.*\)\]/\1/' || true)"
  seed="$(grep -o -- '--seeds=\[[0-9]*\]' <<< "$line" | head -n 1 | tr -dc '0-9' || true)"
  if [ -z "$archive" ] || [ -z "$variant" ] || [ -z "$seed" ]; then
    say "$name: its line names no --archive, one --variants and one --seeds: left alone"; continue
  fi
  rel="$(realpath -m --relative-to=. "$archive")"; run="${variant}_seed${seed}"
  if git ls-files --error-unmatch "$rel/$run/results.json" > /dev/null 2>&1; then
    archived+=("$name"); continue
  fi
  [ -f "$rel/$run/results.json" ] || { say "$name: $rel/$run has no results.json: not archived"; continue; }
  commit="$(sed -n 's/^[^ ]* @\([0-9a-f]\{7,40\}\) .*/\1/p' <<< "$line")"
  cpu="$(grep " start $name on " "$queue.done" | tail -n 1 | sed 's/.* start [^ ]* on //; s/ (tools.*//')"
  bash tools/experiments/queue_archive.sh "$rel" "$name " "$run" \
    "archive: $(basename "$rel"), $variant seed $seed (${commit:-the worker commit}; ${cpu:-CPU not logged})"
  archived+=("$name")
done
[ "${#archived[@]}" -gt 0 ] && [ -f "$pending" ] || exit 0
removed=()
for name in "${archived[@]}"; do
  grep -q "^$name " "$pending" || continue
  grep -v "^$name " "$pending" > "$pending.tmp" || true; mv "$pending.tmp" "$pending"; removed+=("$name")
done
if [ "${#removed[@]}" -gt 0 ]; then
  git commit -q -m "queue: archived runs leave queue_pending (${removed[*]})" -- "$pending"
  git log --oneline -1
fi
