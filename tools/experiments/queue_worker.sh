#!/usr/bin/env bash
# A worker that takes long runs one at a time from a shared queue file, each from a pinned commit's worktree (as
# tools/experiments/pinned.sh: clean provenance, one torch thread), until the queue is empty. Start one worker per
# core on the same queue; append lines to the queue while they run (the next free worker takes them).
#
#   bash tools/experiments/queue_worker.sh <commit> <queue file> <log folder>     # runs in the foreground
#   nohup setsid bash tools/experiments/queue_worker.sh c8c03d9 outputs/q.txt outputs/qlogs > /dev/null 2>&1 &
#
# A queue line is "<name> [@<commit>] [cpu=<family>/<model>,...] <python arguments...>" (e.g. "k3_wo_101 -m
# sr_imitation.experiments.needle_compare ..."): it runs from the worktree of <commit> if the line names one, else of
# the worker's <commit>; a line naming CPU types runs only on a machine of one of them (tools/experiments/cpu_type.sh):
# a worker takes the first line that may run here, leaves the others queued, and stops when none is left. Blank lines
# and lines starting with # are skipped. A taken line is moved to <queue file>.taken, and "<name> rc=<exit status>"
# appended to <queue file>.done when it ends (its start line names the CPU: runs are bit-identical on one CPU type
# only); its output goes to <log folder>/<name>.log. Paths in the arguments
# resolve in the worktree: give output roots and archives as absolute paths. A killed worker's run resumes when its
# line is queued again (tools/experiments/queue_requeue.sh; the runners skip finished runs and resume killed ones).
set -uo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
default_commit="$1"; queue="$(realpath "$2")"; logs="$(mkdir -p "$3" && realpath "$3")"

# shellcheck source=tools/experiments/worktree.sh
source "$root/tools/experiments/worktree.sh"
# shellcheck source=tools/experiments/cpu_type.sh
source "$root/tools/experiments/cpu_type.sh"
# shellcheck source=tools/experiments/isa_env.sh
[ -f "$root/tools/experiments/isa_env.sh" ] && source "$root/tools/experiments/isa_env.sh"

export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
take() {  # under the queue's lock: the first line that may run here, moved from the queue to <queue>.taken
  local line chosen=""
  exec 9>>"$1.lock"; flock 9
  while IFS= read -r line; do
    [[ -z "${line//[[:space:]]/}" || "$line" == \#* ]] && continue
    if line_runs_here "$line"; then chosen="$line"; break; fi
  done < "$1"
  if [ -n "$chosen" ]; then
    grep -v -x -F -e "$chosen" "$1" > "$1.tmp"; mv "$1.tmp" "$1"; echo "$chosen" >> "$1.taken"
  fi
  exec 9>&-
  echo "$chosen"
}

touch "$queue"
while true; do
  line="$(take "$queue")"
  [ -z "$line" ] && break
  name="${line%% *}"; args="${line#* }"; commit="$default_commit"
  if [[ "$args" == @* ]]; then commit="${args%% *}"; commit="${commit#@}"; args="${args#* }"; fi
  [[ "$args" == cpu=* ]] && args="${args#* }"
  cpu="$(cpu_description)"
  isa="${MKL_ENABLE_INSTRUCTIONS:+, libraries capped at $MKL_ENABLE_INSTRUCTIONS (tools/experiments/isa_env.sh)}"
  echo "$(date -u +%FT%TZ) start $name on $cpu$isa" >> "$queue.done"
  if wt="$(pinned_worktree "$root" "$commit")"; then
    # shellcheck disable=SC2086  (the line's arguments are split as a shell splits them, without globbing)
    (cd "$wt" && set -f && export PYTHONPATH="$wt:$wt/policies/lerobot_policy_act_sr:$wt/policies/lerobot_env_sr" \
      && exec "$root/.venv/bin/python" $args) > "$logs/$name.log" 2>&1
    rc=$?
  else
    echo "no worktree for commit $commit" > "$logs/$name.log"; rc=2
  fi
  echo "$(date -u +%FT%TZ) $name rc=$rc" >> "$queue.done"
done
left="$(grep -c -v -e '^[[:space:]]*$' -e '^#' "$queue" || true)"
[ "$left" -gt 0 ] && echo "$(date -u +%FT%TZ) worker stops: the $left line(s) left in $queue name other CPU types" \
  "(this machine: $(cpu_type), $(cpu_description))" >> "$logs/workers.log"
exit 0
