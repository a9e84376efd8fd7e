#!/usr/bin/env bash
# The README's test command: set up everything (virtual environment, pinned dependencies) and run the tests.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
venv="$(bash .ci/venv.sh | tail -n 1)"
# Keep caches that LeRobot, Hugging Face datasets and Mesa write out of $HOME and the network off.
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1
export HF_HOME="${HF_HOME:-$root/.cache/hf}" MESA_SHADER_CACHE_DIR="${MESA_SHADER_CACHE_DIR:-$root/.cache/mesa}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
"$venv/bin/ruff" check sr_imitation policies tests
exec "$venv/bin/python" -m pytest "$@"
