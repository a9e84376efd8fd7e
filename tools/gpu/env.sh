#!/usr/bin/env bash
# Sourced by the device scripts (tools/gpu/run.sh, tools/gpu/sleep_e2e.sh) on the device machine: the carried wheels
# into /tmp/site, the GL loaders, PyAV stubbed (videos off), the image's transformers set aside, PYTHONPATH, $OUT,
# and stamp() for elapsed-time lines. See tools/gpu/prepare.sh for what is carried and why.
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
t0=$(date +%s); stamp() { echo "=== $(( $(date +%s) - t0 )) s: $*"; }
export PYTHONUNBUFFERED=1 MUJOCO_GL=egl WANDB_MODE=offline HF_HUB_OFFLINE=1
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -d /tmp/site/lerobot ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 3
mkdir -p /tmp/site/av && printf '%s\n' '"""Stub: PyAV is not carried to the GPU machine; videos are off there."""' 'import types' \
  'logging = types.SimpleNamespace(WARNING=30, ERROR=40, INFO=20, DEBUG=10, set_level=lambda *a: None, restore_default_callback=lambda: None)' \
  > /tmp/site/av/__init__.py
tf=$(python3 -c "import transformers, os; print(os.path.dirname(transformers.__file__))" 2>/dev/null) && mv "$tf" /tmp/transformers_off
export PYTHONPATH=/tmp/site:$PWD:$PWD/policies/lerobot_policy_act_sr
stamp environment
nvidia-smi -L
python3 -c "import sys, torch; print(sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.cuda.is_available())" || exit 4
# MuJoCo only where its wheel was carried (tools/gpu/grads_sizes.sh leaves it behind: the 64-MiB transfer limit)
if ls .whl/mujoco-*.whl >/dev/null 2>&1; then python3 -c "import mujoco; print('mujoco', mujoco.__version__)" || exit 4; fi
