#!/usr/bin/env bash
# One GPU session's checks, on the device machine (after tools/gpu/prepare.sh here):
#   1. the environment: wheels into /tmp/site, GL loaders, PyAV stubbed (videos off), the image's transformers set
#      aside (LeRobot imports it when present and it needs huggingface_hub 1.x; we carry our pin, 0.35.3);
#   2. python -m sr_imitation.benchmarks.device --device=cuda  -> $OUT/bench_cuda.txt, and
#      python -m sr_imitation.benchmarks.per_memory_grads --device=cuda -> $OUT/per_memory_grads_cuda.txt;
#   3. the two-minute preset as a CUDA stream, state-only, with the camera (ResNet-18) and state-only with
#      --sleep.joint_forward=true (its sleep phases' seconds against the default's), side by side
#      -> $OUT/try_{state,vision,state_joint}_cuda.{txt,tgz} (run directories without weights).
# Everything is written under $OUT; each step has its own time limit, so one failure leaves the others' output.
source "$(dirname "$0")/env.sh"
stamp benchmark
OMP_NUM_THREADS=4 timeout 90 python3 -m sr_imitation.benchmarks.device --device=cuda --threads=4 2>&1 | tee "$OUT/bench_cuda.txt"
OMP_NUM_THREADS=4 timeout 90 python3 -m sr_imitation.benchmarks.per_memory_grads --device=cuda --threads=4 2>&1 \
  | tee "$OUT/per_memory_grads_cuda.txt"
OMP_NUM_THREADS=4 timeout 90 python3 -m sr_imitation.benchmarks.per_memory_grads --device=cuda --threads=4 --k=3 \
  --batch=32 2>&1 | tee "$OUT/per_memory_grads_cuda_k3_b32.txt"  # the presets' sleep sizes (docs/BENCHMARKS.md)
MAIN='import sys; from sr_imitation.main_job import entry; sys.argv = ["sr-main"] + sys.argv[1:]; entry()'
NOVID="--expert_video=false --train.eval.videos_per_skill=0"
stamp "needle_try on cuda: state-only, vision and state-only with joint forward, side by side"
OMP_NUM_THREADS=4 timeout 150 python3 -c "$MAIN" --config_path=configs/needle_try.json $NOVID --train.policy.device=cuda \
  --train.output_dir=/tmp/try_state_cuda > "$OUT/try_state_cuda.txt" 2>&1 &
p1=$!
OMP_NUM_THREADS=4 timeout 150 python3 -c "$MAIN" --config_path=configs/needle_try.json $NOVID --train.policy.device=cuda \
  --train.policy.use_images=true --train.policy.vision_backbone=resnet18 \
  --train.output_dir=/tmp/try_vision_cuda > "$OUT/try_vision_cuda.txt" 2>&1 &
p2=$!
OMP_NUM_THREADS=4 timeout 150 python3 -c "$MAIN" --config_path=configs/needle_try.json $NOVID --train.policy.device=cuda \
  --train.sleep.joint_forward=true --train.output_dir=/tmp/try_state_joint_cuda > "$OUT/try_state_joint_cuda.txt" 2>&1 &
p3=$!
wait $p1; stamp "state rc=$?"; wait $p2; stamp "vision rc=$?"; wait $p3; stamp "state, joint forward rc=$?"
for d in /tmp/try_*; do
  [ -d "$d" ] && tar -czf "$OUT/$(basename "$d").tgz" --exclude='*.safetensors' --exclude='*.mp4' -C /tmp "$(basename "$d")"
done
grep -h "^final\|Error" "$OUT"/try_*.txt | tail -n 6
