#!/usr/bin/env bash
# Write what a queue still has to do, in order, to a file kept in git (tools/experiments/queue_pending.txt), so that
# the next session on any machine continues it: the lines workers took and did not finish (running now, or killed),
# then the queue's own lines, under a dated header saying how to start again. Safe while workers run.
#
#   bash tools/experiments/queue_snapshot.sh outputs/queue.txt tools/experiments/queue_pending.txt [commit]
set -euo pipefail
queue="$(realpath "$1")"; pending="$2"; commit="${3:-c8c03d9}"
flock "$queue.lock" bash -c '
  q="$1"; out="$2"; commit="$3"; : > "$out.tmp"
  unfinished=0
  if [ -f "$q.taken" ]; then
    while IFS= read -r line; do
      name="${line%% *}"
      grep -q -E " $name rc=0$" "$q.done" 2>/dev/null || { echo "$line" >> "$out.lines"; unfinished=$((unfinished + 1)); }
    done < "$q.taken"
  fi
  touch "$out.lines"; grep -v -e "^[[:space:]]*$" -e "^#" "$q" >> "$out.lines" || true
  {
    echo "# The runs still to do, in order (tools/experiments/queue_worker.sh lines), as of $(TZ=UTC date "+%Y-%m-%d %H:%M") UTC:"
    echo "# the first $unfinished were taken by a worker and not finished (they resume where they stopped). To continue:"
    echo "#   grep -v \"^#\" tools/experiments/queue_pending.txt > outputs/queue.txt; rm -f outputs/queue.txt.taken"
    echo "#   nohup setsid bash tools/experiments/queue_worker.sh $commit outputs/queue.txt outputs/qlogs > /dev/null 2>&1 &  # x2"
    echo "# or, on any machine (fresh or not), all of it: bash tools/experiments/queue_resume.sh (the environment, the"
    echo "# datasets the lines read, recorded by tools/experiments/datasets.txt and checked against the archived runs"
    echo "# digests, the queue file, the workers)"
    echo "# each finished run (its driver archived it): bash tools/experiments/queue_archive.sh <archive> <prefix> <run> <message>"
    cat "$out.lines"
  } > "$out.tmp"
  rm -f "$out.lines"; mv "$out.tmp" "$out"
  echo "$out: $(grep -c -v "^#" "$out") line(s), $unfinished unfinished"' _ "$queue" "$pending" "$commit"
