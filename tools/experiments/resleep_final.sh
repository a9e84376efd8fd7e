#!/usr/bin/env bash
# Issue 89 items 3-4: re-sleep a finished SR run's final stage from its stored newest wake and memories with sr-sleep,
# the run's sleep settings and its final sleep's own seed (seed * 1000 + 10 k + 3), evaluating every skill before and
# after in the run's own evaluation (episodes, seeds, steps, thresholds); only the candidate's settings differ:
#   anchor_off     C1: --sleep.anchor_strength=0 (no anchor)
#   anchor_newest  C2: the run's lambda, no --anchor.path: the deployed policy, the newest wake, is the anchor
#   guard          C3: the run's own sleep (--anchor.path = stage k-1's consolidated checkpoint, --final_skill=true)
#                  with --sleep.newest_guard=true
#   own            the run's own sleep repeated (as guard, without the guard): a check that sr-sleep repeats it
# (the final-sleep screening protocol in docs/RESULTS.md). Run it while the run folder exists (outputs/ is not kept
# across machines); the output folder (sleep.json, sleep.md) goes to the run's archive.
#
#   bash tools/experiments/resleep_final.sh <run dir> <output dir> <candidate>
#   e.g. bash tools/experiments/resleep_final.sh outputs/order_mt5_screening_reverse/sr_100/sr_seed100 \
#        docs/results/order_mt5_screening_reverse/sr_seed100_final_sleep_guard guard
set -euo pipefail
[ $# -eq 3 ] || { echo "usage: resleep_final.sh <run dir> <output dir> anchor_off|anchor_newest|guard|own" >&2; exit 2; }
run="$1"; out="$2"; candidate="$3"
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
py="$root/.venv/bin/python"
args="$("$py" - "$run" "$candidate" <<'PY'
import json, sys
from pathlib import Path
from sr_imitation.stream.substrate import phase_seed
run, candidate = Path(sys.argv[1]), sys.argv[2]
cfg = json.loads((run / "train_config.json").read_text())
skills = cfg["stream"]["skills"]
k = len(skills)
s, e = cfg["sleep"], cfg["eval"]
if s["anchor_tau"] is not None:
    sys.exit(f"resleep_final: {run}: anchor_tau={s['anchor_tau']}: only an always-on anchor is re-slept here")
memories = ",".join(str(run / "memories" / f"skill_{i + 1}_{n}.safetensors") for i, n in enumerate(skills))
previous = run / f"skill_{k - 1}_{skills[-2]}" / "sleep" / "pretrained_model"  # theta_{k-1}^sleep
by_candidate = {
    "anchor_off": ["--sleep.anchor_strength=0"],
    "anchor_newest": [f"--sleep.anchor_strength={s['anchor_strength']}", "--final_skill=true"],
    "guard": [f"--sleep.anchor_strength={s['anchor_strength']}", f"--anchor.path={previous}", "--final_skill=true",
              "--sleep.newest_guard=true"],
    "own": [f"--sleep.anchor_strength={s['anchor_strength']}", f"--anchor.path={previous}", "--final_skill=true"],
}
if candidate not in by_candidate:
    sys.exit(f"resleep_final: candidate {candidate!r}: give one of {', '.join(by_candidate)}")
args = [f"--policy.path={run / f'skill_{k}_{skills[-1]}' / 'wake' / 'pretrained_model'}", f"--memories=[{memories}]",
        f"--sleep.lr={s['lr']}", f"--sleep.max_iterations={s['max_iterations']}", f"--sleep.batch_size={s['batch_size']}",
        f"--sleep.early_stop_window={s['early_stop_window']}", f"--sleep.early_stop_tol={s['early_stop_tol']}",
        f"--sleep.aggregator={s['aggregator']}", f"--sleep.anchor_after_final={str(s['anchor_after_final']).lower()}",
        *by_candidate[candidate],
        f"--sleep.seed={phase_seed('decimal', cfg['seed'], k - 1, 'sleep')}",  # the run's final sleep's own seed
        f"--eval.skills=[{','.join(skills)}]", f"--eval.env={e['env']}", f"--eval.episodes={e['episodes']}",
        f"--eval.seeds=[{','.join(map(str, e['seeds']))}]", f"--eval.max_steps={e['max_steps']}",
        f"--eval.thresholds={e['thresholds']}", "--eval.videos_per_skill=0"]
print("\n".join(args))
PY
)"
mapfile -t settings <<< "$args"
OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" ${SR_SLEEP_BIN:-"$root/.venv/bin/sr-sleep"} "${settings[@]}" \
  "--output_dir=$out" --progress=false
