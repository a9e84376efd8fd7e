#!/usr/bin/env bash
# Commit one finished queue run's archived raw output (the driver's --archive already copied it) with the queue's
# record of it: the archive's queue_log.txt gains every "<prefix>..." line of the queue's .done file (its header line
# kept, lines sorted and unique), then exactly those two paths are committed. Never during a full test run
# (tests/infra/test_provenance.py fails when HEAD moves under it).
#
#   bash tools/experiments/queue_archive.sh <archive dir> <queue name prefix> <run dir name> <message>
#   e.g. bash tools/experiments/queue_archive.sh docs/results/metaworld_mt5_imitation_compare mt5_ replay_seed3 \
#        "raw output: MT5 imitation test run, replay seed 3 (...)"
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
archive="$1"; prefix="$2"; run="$3"; message="$4"; done_file="outputs/queue.txt.done"
[ -d "$archive/$run" ] || { echo "queue_archive: $archive/$run: no such archived run" >&2; exit 2; }
log="$archive/queue_log.txt"
if [ ! -f "$log" ]; then  # the first run archived here: the log starts with its header line
  echo "# Start and end (exit status) of each run archived here, as the queue worker logged them (UTC;" \
    "tools/experiments/queue_worker.sh), merged over sessions." > "$log"
fi
{ head -1 "$log"; { tail -n +2 "$log"; grep " $prefix" "$done_file" || true; } | sort -u; } > "$log.tmp"
mv "$log.tmp" "$log"
git add "$archive/$run" "$log"
git commit -q -m "$message" -- "$archive/$run" "$log"
git log --oneline -1
