# Sourced by .ci/test.sh and .ci/main.sh: build or reuse the environments and set $venv to this clone's own one,
# <clone>/.venv (this clone's code over the shared dependency venv; see .ci/venv.sh), and keep LeRobot, Hugging Face
# datasets and Mesa offline and their caches inside the clone; offscreen rendering through EGL.
venv="$(bash "$root/.ci/venv.sh" | tail -n 1)"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1
export HF_HOME="${HF_HOME:-$root/.cache/hf}" MESA_SHADER_CACHE_DIR="${MESA_SHADER_CACHE_DIR:-$root/.cache/mesa}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
