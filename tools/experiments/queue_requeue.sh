#!/usr/bin/env bash
# Put back at the front of a queue the lines workers took but did not finish (a worker killed at a session's end):
# run it once, while no worker of that queue runs, then start the workers again; each run resumes where it stopped.
#
#   bash tools/experiments/queue_requeue.sh outputs/queue.txt
set -euo pipefail
queue="$(realpath "$1")"
if pgrep -f "queue_worker.sh .* $1" >/dev/null || pgrep -f "queue_worker.sh .* $queue" >/dev/null; then
  echo "a worker of $1 is running: stop it first (its run would be started twice)" >&2; exit 2
fi
[ -f "$queue.taken" ] || { echo "nothing taken from $1"; exit 0; }
flock "$queue.lock" bash -c '
  q="$1"; : > "$q.back"
  while IFS= read -r line; do
    name="${line%% *}"
    grep -q -E " $name rc=0$" "$q.done" 2>/dev/null || echo "$line" >> "$q.back"
  done < "$q.taken"
  n=$(grep -c . "$q.back" || true)
  cat "$q.back" "$q" > "$q.new" && mv "$q.new" "$q"
  grep -v -x -F -f "$q.back" "$q.taken" > "$q.taken.new" || true; mv "$q.taken.new" "$q.taken"; rm -f "$q.back"
  echo "requeued $n unfinished line(s) at the front of $q"' _ "$queue"
