#!/usr/bin/env bash
# Issue 89 items 3-4 for every archived SR run of the named archives: re-sleep its final stage as a candidate of
# tools/experiments/resleep_final.sh (--candidate=anchor_off, the default; anchor_newest, guard or own) while the run's
# outputs exist, keep the re-sleep's record (sleep.json, sleep.md, sleep_diagnostics.json; not its checkpoint) as
# <archive>/sr_seed<S>_final_sleep_<candidate>/ and commit it.
# The run's outputs are found from the queue line that archived it (--archive=<archive>, --variants=[sr],
# --seeds=[<S>] in outputs/queue.txt.taken; the run is <--output_root>/sr_seed<S>). A run already re-slept, not yet
# committed, or whose outputs are gone is named and skipped; a re-sleep that fails or is killed leaves nothing behind
# (run the script again). Never during a full test run (tests/infra/test_provenance.py fails when HEAD moves under it).
#
#   bash tools/experiments/resleep_archived.sh docs/results/order_mt5_imitation_reverse docs/results/lerobot06_mt5_imitation
#   bash tools/experiments/resleep_archived.sh --candidate=guard docs/results/order_mt5_screening_reverse
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
taken="outputs/queue.txt.taken"
resleep="${SR_RESLEEP:-bash tools/experiments/resleep_final.sh}"  # tests put a stand-in here
say() { echo "resleep_archived: $*" >&2; }
candidate=anchor_off
case "${1:-}" in --candidate=*) candidate="${1#--candidate=}"; shift;; esac
case "$candidate" in
  anchor_off) what="with the anchor off (sr-sleep --sleep.anchor_strength=0)";;
  anchor_newest) what="with the anchor toward the newest wake (sr-sleep without --anchor.path)";;
  guard) what="with the newest-skill guard (sr-sleep --sleep.newest_guard=true)";;
  own) what="as the run slept it (sr-sleep --anchor.path=<stage k-1's consolidated checkpoint>)";;
  *) say "--candidate=$candidate: give anchor_off, anchor_newest, guard or own"; exit 2;;
esac
for archive in "$@"; do
  archive="${archive%/}"
  [ -d "$archive" ] || { say "$archive: no such archive"; exit 2; }
  abs="$(realpath "$archive")"
  for dir in "$archive"/sr_seed*; do
    name="$(basename "$dir")"
    [[ "$name" =~ ^sr_seed([0-9]+)$ ]] || continue
    seed="${BASH_REMATCH[1]}"; out="$archive/${name}_final_sleep_$candidate"
    [ -f "$out/sleep.json" ] && continue
    git ls-files --error-unmatch "$dir/results.json" > /dev/null 2>&1 || { say "$dir: not committed yet: skipped"; continue; }
    line="$(awk -v a="--archive=$abs" -v s="--seeds=[$seed]" '
      { sr = 0; sd = 0; ar = 0
        for (i = 1; i <= NF; i++) { if ($i == "--variants=[sr]") sr = 1; if ($i == s) sd = 1; if ($i == a) ar = 1 }
        if (sr && sd && ar) { print; exit } }' "$taken" 2>/dev/null || true)"
    root="$(grep -o -- '--output_root=[^ ]*' <<< "$line" | head -n 1 | cut -d= -f2- || true)"
    src="$root/$name"
    if [ -z "$root" ] || [ ! -d "$src/memories" ]; then
      say "$dir: its outputs (${root:+$src}${root:-no queue line names it}) are gone: not re-slept"; continue
    fi
    rm -rf "$out"
    log="outputs/resleep_$(basename "$archive")_${seed}_$candidate.log"
    say "$dir: re-sleeping its final stage $what (log $log)"
    if ! $resleep "$src" "$out" "$candidate" > "$log" 2>&1 || [ ! -f "$out/sleep.json" ]; then
      rm -rf "$out"; say "$dir: the re-sleep failed (see its log): nothing kept"; continue
    fi
    rm -rf "$out/pretrained_model" "$out/checksums.json"
    git add "$out"
    git commit -q -m "archive: $(basename "$archive"), sr seed $seed's final stage re-slept $what" -- "$out"
    git log --oneline -1
  done
done
