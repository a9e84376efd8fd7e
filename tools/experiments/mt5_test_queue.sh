#!/usr/bin/env bash
# Print the queue lines (tools/experiments/queue_worker.sh) of the MT5 imitation stream's test runs, as the protocol
# in docs/RESULTS.md lists them, ordered so that the test family's pairs complete seed by seed: sr, wake_only and
# replay on seed 0, then seed 1, ... 9; then sequential_bc and mt_joint on seeds 0-9; then the descriptive baselines
# (ewc_lam10000, lwf_w0.1, m2distill_w0.01) on seeds 0-2. Give the calibrated flags exactly as the dated line below
# the protocol records them (one --extra value):
#
#   bash tools/experiments/mt5_test_queue.sh '--extra=[--stream.dataset_root=datasets/metaworld_mt5_d100,...]' >> outputs/queue.txt
set -euo pipefail
extra="$1"
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
archive="$root/docs/results/metaworld_mt5_imitation_compare"
out="$root/outputs/metaworld_mt5_imitation"
line() {  # <variant> <seed>
  echo "mt5_${1}_$2 -m sr_imitation.experiments.needle_compare --preset=configs/metaworld_mt5_imitation.json $extra" \
       "--variants=[$1] --seeds=[$2] --output_root=$out/${1}_$2 --archive=$archive"
}
for seed in 0 1 2 3 4 5 6 7 8 9; do for v in sr wake_only replay; do line "$v" "$seed"; done; done
for seed in 0 1 2 3 4 5 6 7 8 9; do for v in sequential_bc mt_joint; do line "$v" "$seed"; done; done
for seed in 0 1 2; do for v in ewc_lam10000 lwf_w0.1 m2distill_w0.01; do line "$v" "$seed"; done; done
