#!/usr/bin/env bash
# Prepare a GPU session (run HERE, on the project VM, before the first device call; needs the pip index).
#
# The lent GPU machines run this workplace's CUDA image: Python 3.12, torch 2.11 (cu130), numpy 2.5, no LeRobot,
# no MuJoCo, nothing reachable. What our code needs beyond the image travels with the working tree (<= 64 MiB):
#   .whl/   cp312 wheels of LeRobot 0.6.1 and the dependencies the image lacks, at our pins (the list was written
#           for LeRobot 0.4.4's lock and moved to 0.6.1's on 2026-12-07; no device session has used it since)
#   .gl/    the GL loader packages for MuJoCo's EGL rendering on the NVIDIA driver (~0.4 MB)
#   datasets/needle_try   recorded here: LeRobot + datasets 4.8.5 could not record under the image's numpy 2.5
#           (Value.encode_example calls float() on a shape-(1,) array), so demonstrations are recorded on the VM
# PyAV (39 MB) does not fit: tools/gpu/run.sh stubs it and turns videos off. All three paths are git-ignored
# through .git/info/exclude (local only).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
mkdir -p .git/info
for p in /.whl/ /.gl/; do grep -qxF "$p" .git/info/exclude 2>/dev/null || echo "$p" >> .git/info/exclude; done
pin() { grep -i "^$1==" .ci/constraints.txt | head -1; }
mkdir -p .whl
plat="--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any"
for name in lerobot draccus mergedeep toml typing-inspect mypy-extensions datasets dill multiprocess huggingface-hub \
            hf-xet pydantic pydantic_core typing-inspection annotated-types termcolor gymnasium \
            Farama-Notifications mujoco PyOpenGL glfw jsonlines; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $plat \
    -d .whl "$(pin "$name")" 2>&1 | grep -v "^WARNING: Location" || true
done
mkdir -p .gl /tmp/amd64/partial
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
apt-get $o update -qq >/dev/null
(cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 2>/dev/null)
[ -d datasets/needle_try ] || OMP_NUM_THREADS=1 MUJOCO_GL=egl .venv/bin/sr-record --skills=[approach,place,insert] \
  --num_episodes=15 --root=datasets/needle_try --image_size=32 --seed=0 --demo_threshold_scale=0.5 --expert_jaw_close_mm=0.5
du -sh .whl .gl datasets/needle_try
echo "tracked files: $(git ls-files -z | du -cb --files0-from=- | tail -1 | cut -f1) bytes (with the above: <= 64 MiB)"
echo "then: device run 'bash tools/gpu/run.sh' with carry [.whl, .gl, datasets/needle_try]"
