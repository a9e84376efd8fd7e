#!/usr/bin/env bash
# The README's main-job command: set up the environment (as the test command does), then run the main job on
# the embedded CPU preset: record expert demos, run the five-skill wake-sleep stream with evaluation after
# every phase, and write tables, plots and videos. Extra arguments go to sr-main, e.g.
#   bash .ci/main.sh --config_path=configs/needle_paper.json
#   bash .ci/main.sh --train.resume=true          # continue a run that was interrupted
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
venv="$(bash .ci/venv.sh | tail -n 1)"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1
export HF_HOME="${HF_HOME:-$root/.cache/hf}" MESA_SHADER_CACHE_DIR="${MESA_SHADER_CACHE_DIR:-$root/.cache/mesa}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
has_config=false
for arg in "$@"; do case "$arg" in --config_path=*) has_config=true ;; esac; done
if [ "$has_config" = true ]; then
  exec "$venv/bin/sr-main" "$@"
fi
exec "$venv/bin/sr-main" --config_path=configs/needle_cpu.json "$@"
