#!/usr/bin/env bash
# Issue 89 item 3: re-sleep a finished SR run's final stage from its stored wake and memories with the anchor off
# (sr-sleep, --sleep.anchor_strength=0, the run's other sleep settings and its final sleep's own seed, seed * 1000 +
# 10 k + 3, so that only the anchor differs from the run's sleep), evaluating every skill before and after in the
# run's own evaluation (episodes, seeds, steps, thresholds). Before 2026-12-07 16:00 UTC it passed the config's base
# --sleep.seed (0) instead: the re-sleeps of that day kept as sr_seed<S>_final_sleep_anchor_off_sampler0/. Run it
# while the run folder exists (outputs/ is not kept across machines); the output folder (sleep.json, sleep.md) goes
# to the run's archive.
#
#   bash tools/experiments/resleep_anchor_off.sh <run dir> <output dir>
#   e.g. bash tools/experiments/resleep_anchor_off.sh outputs/lerobot06_needle_m16/sr_0/sr_seed0 \
#        docs/results/lerobot06_needle_m16/sr_seed0_final_sleep_anchor_off
set -euo pipefail
run="$1"; out="$2"
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
py="$root/.venv/bin/python"
read -r wake memories args < <("$py" - "$run" <<'PY'
import json, sys
from pathlib import Path
from sr_imitation.stream.substrate import phase_seed
run = Path(sys.argv[1])
cfg = json.loads((run / "train_config.json").read_text())
skills = cfg["stream"]["skills"]
k = len(skills)
wake = run / f"skill_{k}_{skills[-1]}" / "wake" / "pretrained_model"
memories = ",".join(str(run / "memories" / f"skill_{i + 1}_{s}.safetensors") for i, s in enumerate(skills))
s, e = cfg["sleep"], cfg["eval"]
args = [f"--sleep.lr={s['lr']}", f"--sleep.max_iterations={s['max_iterations']}", f"--sleep.batch_size={s['batch_size']}",
        f"--sleep.early_stop_window={s['early_stop_window']}", f"--sleep.early_stop_tol={s['early_stop_tol']}",
        f"--sleep.aggregator={s['aggregator']}", "--sleep.anchor_strength=0",
        f"--sleep.seed={phase_seed('decimal', cfg['seed'], k - 1, 'sleep')}",  # the run's final sleep's own seed
        f"--eval.skills=[{','.join(skills)}]", f"--eval.env={e['env']}", f"--eval.episodes={e['episodes']}",
        f"--eval.seeds=[{','.join(map(str, e['seeds']))}]", f"--eval.max_steps={e['max_steps']}",
        f"--eval.thresholds={e['thresholds']}", "--eval.videos_per_skill=0"]
print(wake, memories, " ".join(args))
PY
)
# shellcheck disable=SC2086  (the settings are split as a shell splits them)
OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" ${SR_SLEEP_BIN:-"$root/.venv/bin/sr-sleep"} "--policy.path=$wake" "--memories=[$memories]" \
  "--output_dir=$out" --progress=false $args
