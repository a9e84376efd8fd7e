#!/usr/bin/env bash
# Whole sleep iterations on CUDA with and without --sleep.joint_forward, memories as the stream writes them, before
# and after ActorMemory.provenance_keys (python -m sr_imitation.benchmarks.sleep_joint_forward; docs/BENCHMARKS.md):
# at the stream's sizes (k = 2 and 3 memories, batch 32, state-only; k = 3, batch 32, with the camera) and at the
# device benchmark's (k = 5, batch 8), one call on one GPU, nothing beside it. Carry as tools/gpu/grads_sizes.sh says.
# Writes $OUT/sleep_joint_forward_cuda_<policy>_k<k>_b<batch>.txt.
source "$(dirname "$0")/env.sh"
for size in "state 3 32" "state 2 32" "vision 3 32" "state 5 8"; do
  set -- $size
  flag=""; [ "$1" = vision ] && flag="--vision"
  stamp "sleep_joint_forward $1 k=$2 batch=$3"
  OMP_NUM_THREADS=4 timeout 150 python3 -m sr_imitation.benchmarks.sleep_joint_forward --device=cuda --threads=4 \
    --k="$2" --batch="$3" $flag 2>&1 | tee "$OUT/sleep_joint_forward_cuda_$1_k$2_b$3.txt"
done
stamp done
