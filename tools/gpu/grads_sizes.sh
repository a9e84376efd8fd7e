#!/usr/bin/env bash
# The per-memory gradients on CUDA at the stream's sleep sizes (docs/BENCHMARKS.md, "It does not hold end to end"):
# 2026-11-26's GPU session measured joint forward 2.9x faster than the k passes at k = 5 memories, batch 8, but no
# faster in the stream, whose sleeps draw batches of 32 from k = 2-3 memories. This runs the benchmark at the
# benchmark's size and at the stream's two, in one call on one GPU (so the three are paired), nothing beside it.
# On the device machine after tools/gpu/prepare.sh here, carrying only .whl (without the MuJoCo, PyOpenGL and glfw
# wheels, which this benchmark does not import: with them the tree passes the 64-MiB transfer limit):
#   mkdir -p /tmp/whl_off && mv .whl/mujoco-* .whl/pyopengl-* .whl/glfw-* /tmp/whl_off/
#   device run 'bash tools/gpu/grads_sizes.sh' with carry [.whl]; then mv /tmp/whl_off/* .whl/
# Writes $OUT/per_memory_grads_cuda_k<k>_b<batch>.txt.
source "$(dirname "$0")/env.sh"
for size in "5 8" "3 32" "2 32"; do
  set -- $size
  stamp "per_memory_grads k=$1 batch=$2"
  OMP_NUM_THREADS=4 timeout 120 python3 -m sr_imitation.benchmarks.per_memory_grads --device=cuda --threads=4 \
    --k="$1" --batch="$2" 2>&1 | tee "$OUT/per_memory_grads_cuda_k$1_b$2.txt"
done
stamp done
