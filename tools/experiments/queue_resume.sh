#!/usr/bin/env bash
# Continue tools/experiments/queue_pending.txt on this machine, fresh or not, in one command (a new session's first):
#   1. the environment (.ci/venv.sh; reused when built);
#   2. every dataset of tools/experiments/datasets.txt that a pending line reads (--stream.dataset_root=datasets/<x>)
#      and this clone lacks: recorded from its commit's worktree, one skill per process, two at a time; then each
#      such dataset's content digests are checked against the archived run the manifest names, and a mismatch stops
#      here, before any run (another CPU type can record other demonstrations: RESULTS must not mix them);
#   3. outputs/queue.txt from the pending file (unless a queue file is already there, or workers of this clone run:
#      it is never overwritten, and no pending line is queued twice);
#   4. workers (tools/experiments/queue_worker.sh, commit of the pending file's header) up to one per core, 2 at most;
#      a line naming other CPU types (cpu=<family>/<model>,...: tools/experiments/cpu_type.sh) is queued but waits.
#
#   bash tools/experiments/queue_resume.sh            # all of it
#   bash tools/experiments/queue_resume.sh --dry-run  # say what it would do; change nothing
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
root="$(pwd)"; pending="tools/experiments/queue_pending.txt"; manifest="tools/experiments/datasets.txt"
dry=0; [ "${1:-}" = "--dry-run" ] && dry=1
say() { echo "queue_resume: $*" >&2; }
run() { if [ "$dry" = 1 ]; then say "would run: $*"; else "$@"; fi; }

[ -f "$pending" ] || { say "$pending: no such file"; exit 2; }
commit="$(grep -o -m1 'queue_worker.sh [0-9a-f]\{7,40\}' "$pending" | awk '{print $2}')"
[ -n "$commit" ] || { say "$pending: its header names no worker commit (queue_worker.sh <commit>)"; exit 2; }
lines="$(grep -v -e '^[[:space:]]*$' -e '^#' "$pending" || true)"
[ -n "$lines" ] || { say "$pending: nothing left to run"; exit 0; }

py="$root/.venv/bin/python"; [ "$dry" = 1 ] || py="$(bash .ci/venv.sh | tail -n 1)/bin/python"

# shellcheck source=tools/experiments/worktree.sh
source tools/experiments/worktree.sh
# shellcheck source=tools/experiments/cpu_type.sh
source tools/experiments/cpu_type.sh
# shellcheck source=tools/experiments/isa_env.sh
[ -f tools/experiments/isa_env.sh ] && source tools/experiments/isa_env.sh  # recordings too: the workers' code paths
for folder in $(grep -o 'dataset_root=datasets/[A-Za-z0-9_.-]*' <<< "$lines" | sort -u | cut -d/ -f2); do
  entry="$(grep -v '^#' "$manifest" | awk -v f="$folder" '$1 == f' | head -n 1)"
  [ -n "$entry" ] || { say "datasets/$folder: read by a pending line, not in $manifest (add its recipe)"; exit 2; }
  read -r _ rec_commit reference flags <<< "$entry"
  skills="$(python3 -c 'import json, sys
s = json.load(open(sys.argv[1]))["settings"]
print(" ".join(k.split(".", 2)[2] for k in sorted(s) if k.startswith("inputs.datasets.")))' \
    "$reference/settings_fingerprint.json")"
  missing=""
  for skill in $skills; do [ -f "datasets/$folder/$skill/meta/info.json" ] || missing="$missing $skill"; done
  if [ -n "$missing" ]; then
    say "datasets/$folder: recording$missing from $rec_commit (sr-record $flags)"
    if [ "$dry" = 0 ]; then
      mkdir -p "datasets/$folder"
      wt="$(pinned_worktree "$root" "$rec_commit")"
      # shellcheck disable=SC2086  (the manifest's flags are split as a shell splits them)
      printf '%s\n' $missing | (cd "$wt" && export PYTHONPATH="$wt" OMP_NUM_THREADS=1 MUJOCO_GL="${MUJOCO_GL:-egl}" \
        && xargs -P 2 -I{} "$py" -c 'from sr_imitation.recorders.cli import entry; entry()' $flags \
             "--root=$root/datasets/$folder" "--skills=[{}]") \
        || { say "datasets/$folder: recording failed"; exit 1; }
    fi
  fi
  if [ "$dry" = 0 ]; then
    "$py" - "$root/datasets/$folder" "$reference/settings_fingerprint.json" <<'PY' || exit 1
import json, sys
from pathlib import Path
from sr_imitation.substrates.act.dataset_identity import dataset_digest
folder, reference = Path(sys.argv[1]), sys.argv[2]
settings = json.load(open(reference))["settings"]
bad = [k.split(".", 2)[2] for k, v in sorted(settings.items())
       if k.startswith("inputs.datasets.") and dataset_digest(folder / k.split(".", 2)[2]) != v]
if bad:
    sys.exit(f"queue_resume: {folder}: {', '.join(bad)} differ from the digests of {reference} (another recorder or "
             "CPU type?); no run started. Move the folder away and find out why before queueing.")
print(f"queue_resume: {folder}: the same digests as {reference}", file=sys.stderr)
PY
  fi
done

workers() {  # this clone's workers: queue_worker.sh processes started here (their working folder is this clone)
  local n=0 p
  for p in $(pgrep -f 'queue_worker.sh .* outputs/queue.txt' || true); do
    [ "$(readlink "/proc/$p/cwd" 2>/dev/null)" = "$root" ] && n=$((n + 1))
  done
  echo "$n"
}
running="$(workers)"
mkdir -p outputs
if [ "$running" -gt 0 ]; then
  say "$running worker(s) of this clone running: outputs/queue.txt left as it is (the pending lines may be running now)"
elif [ -s outputs/queue.txt ]; then
  say "outputs/queue.txt exists ($(grep -c -v -e '^#' -e '^[[:space:]]*$' outputs/queue.txt || true) line(s)): kept as it is"
elif [ "$dry" = 1 ]; then
  say "would write outputs/queue.txt: $(wc -l <<< "$lines") line(s) from $pending"
else
  printf '%s\n' "$lines" > outputs/queue.txt; rm -f outputs/queue.txt.taken
  say "outputs/queue.txt: $(wc -l <<< "$lines") line(s) from $pending"
fi

# Lines that name other CPU types stay queued for a machine of their type (queue_worker.sh takes only the others).
waiting=""
while IFS= read -r line; do
  line_runs_here "$line" || waiting="$waiting ${line%% *}"
done <<< "$lines"
[ -z "$waiting" ] || say "waiting for another CPU type (this machine is $(cpu_type)), not run here:$waiting"

cores="$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)"  # nproc obeys OMP_NUM_THREADS, which runs set to 1
want=$(( cores < 2 ? cores : 2 ))
for _ in $(seq $((running + 1)) "$want"); do
  if [ "$dry" = 1 ]; then say "would start a worker (commit $commit)"; continue; fi
  nohup setsid bash tools/experiments/queue_worker.sh "$commit" outputs/queue.txt outputs/qlogs > /dev/null 2>&1 &
  sleep 2
done
[ "$dry" = 1 ] || say "workers running: $(workers); logs in outputs/qlogs"
