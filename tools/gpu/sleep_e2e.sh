#!/usr/bin/env bash
# Does --sleep.joint_forward=true shorten a stream's sleep phases on CUDA end to end (not only in the benchmark)?
# The two-minute preset (configs/needle_try.json), state-only and with the camera, each with the default k-pass
# sleep and with joint forward, one run at a time on the GPU (nothing beside it), on the device machine after
# tools/gpu/prepare.sh here. Prints each sleep phase's seconds and iterations from the run's progress.json;
# writes $OUT/e2e_<name>.txt (the run's log) and $OUT/sleep_e2e.txt (the table).
# The tracked tree with the carried paths passes the 64-MiB transfer limit; leave docs/results/ out for the call:
#   mv docs/results /tmp/results_off; device run 'bash tools/gpu/sleep_e2e.sh' with carry [.whl, .gl,
#   datasets/needle_try]; mv /tmp/results_off docs/results   (nothing may write docs/results/ meanwhile)
source "$(dirname "$0")/env.sh"
MAIN='import sys; from sr_imitation.main_job import entry; sys.argv = ["sr-main"] + sys.argv[1:]; entry()'
NOVID="--expert_video=false --train.eval.videos_per_skill=0"
# 5 epochs per wake with the camera (the preset has 30): at 30 the camera runs do not reach their first sleep inside
# the 120-s limit of 2026-11-28 (now 150 s); the sleeps, what this measures, keep their sizes and iteration counts.
VISION="--train.policy.use_images=true --train.policy.vision_backbone=resnet18 --train.wake.max_epochs=5 --train.wake.min_epochs=5"
table() {  # the table so far (rewritten after each run, so a call cut short still brings back the finished rows)
python3 - <<'PY' > "$OUT/sleep_e2e.txt"
import json, os
print("| run | sleep phase | iterations | seconds | ms per iteration |\n|---|---|---|---|---|")
for name in ("state", "state_joint", "vision", "vision_joint"):
    path = f"/tmp/e2e_{name}/progress.json"
    if not os.path.exists(path):
        print(f"| {name} | (no progress.json) | | | |"); continue
    done = json.load(open(path))["completed"]
    for phase in sorted(k for k in done if k.endswith(".sleep")):
        n, s = done[phase]["stop_iteration"], done[phase]["seconds"]
        print(f"| {name} | {phase} | {n} | {s:.2f} | {1000 * s / n:.1f} |")
PY
}
for name in state state_joint vision vision_joint; do
  extra=""; case $name in vision*) extra="$VISION";; esac
  case $name in *joint) extra="$extra --train.sleep.joint_forward=true";; esac
  stamp "$name"
  OMP_NUM_THREADS=4 timeout 150 python3 -c "$MAIN" --config_path=configs/needle_try.json $NOVID --train.policy.device=cuda \
    $extra --train.output_dir=/tmp/e2e_$name > "$OUT/e2e_$name.txt" 2>&1
  echo "rc=$?"; table
done
stamp done
cat "$OUT/sleep_e2e.txt"
