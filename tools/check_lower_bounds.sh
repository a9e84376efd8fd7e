#!/usr/bin/env bash
# Test the lower bounds of pyproject.toml's dependency ranges (.ci/lower_bounds.txt): a throwaway environment under
# /tmp whose own site-packages holds exactly those versions (from the package index), over the shared dependency venv
# (everything else at the lock, .ci/constraints.txt), with this checkout installed in editable mode; then `pip check`
# and a subset of the tests that exercises those libraries. Nothing outside the throwaway environment is changed (the
# shared venv is only read; the script fails if its package list changed).
#
#   bash tools/check_lower_bounds.sh [pytest arguments]      # e.g. -x -q; added to the subset below
#
# The dependency venv is the one this clone's .venv reaches (bash .ci/venv.sh builds both); SR_SHARED_VENV=/path names
# another. SR_LB_TESTS="tests/..." replaces the test subset; SR_LB_KEEP=1 keeps the throwaway environment.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
started=$(date +%s)

shared="${SR_SHARED_VENV:-}"
if [ -z "$shared" ]; then
  site="$("$root/.venv/bin/python" -I .ci/overlay.py shared-site "$root/.venv")"
  shared="$(dirname "$(dirname "$(dirname "$site")")")"  # <venv>/lib/pythonX.Y/site-packages -> <venv>
fi
[ -x "$shared/bin/python" ] || { echo "[lower-bounds] no dependency venv at $shared (run bash .ci/venv.sh)" >&2; exit 1; }
shared_site="$("$shared/bin/python" -I -c "import sysconfig; print(sysconfig.get_path('purelib'))")"

tmp="$(mktemp -d /tmp/sr_lower_bounds.XXXXXX)"
if [ "${SR_LB_KEEP:-0}" = "1" ]; then
  echo "[lower-bounds] keeping $tmp" >&2
else
  trap 'rm -rf "$tmp"' EXIT
fi
env_dir="$tmp/venv"
py="$env_dir/bin/python"
listing() { ls -1 "$shared_site" | sha256sum; }
before="$(listing)"

# The overlay layout of .ci/venv.sh: a venv whose one .pth adds the shared site-packages behind its own.
"$shared/bin/python" -I .ci/overlay.py create "$shared" "$env_dir"
own_site="$("$py" -I -c "import sysconfig; print(sysconfig.get_path('purelib'))")"
echo "[lower-bounds] throwaway environment $env_dir over $shared_site" >&2
# The shared venv's pip (reached through the .pth) installs into the throwaway venv's own site-packages, which comes
# first on sys.path: these versions shadow the locked ones. --ignore-installed: never uninstall the shadowed copies.
if ! (cd "$tmp" && PYTHONWARNINGS=ignore "$py" -I -m pip install --quiet --no-deps --ignore-installed \
      --only-binary=:all: -r "$root/.ci/lower_bounds.txt" >"$tmp/pip.log" 2>&1); then
  grep -v "is ignored: it is neither" "$tmp/pip.log" >&2
  echo "[lower-bounds] installing .ci/lower_bounds.txt failed" >&2
  exit 1
fi
# This checkout, as .ci/venv.sh installs it (-P: the checkout's own egg-info is not on sys.path).
PYTHONWARNINGS=ignore "$py" -P -m pip install --quiet --no-deps --no-build-isolation --no-index \
  -e . -e policies/lerobot_policy_act_sr -e policies/lerobot_env_sr >&2

echo "[lower-bounds] $(date -u '+%Y-%m-%d %H:%M UTC'), commit $(git rev-parse --short HEAD)$(git diff --quiet HEAD || echo '+changes'),$(lscpu | sed -n 's/^Model name: *\(.*\)/ \1/p' | head -1)"
# The versions actually imported: every lower bound from the throwaway site-packages, the rest from the lock.
"$py" - "$root/.ci/lower_bounds.txt" "$own_site" <<'PY'
import importlib
import importlib.metadata as md
import sys
from pathlib import Path

from packaging.requirements import Requirement

bounds = {}
for line in Path(sys.argv[1]).read_text().splitlines():
    line = line.split("#", 1)[0].strip()
    if line:
        req = Requirement(line)
        bounds[req.name] = str(next(iter(req.specifier)).version)
own = Path(sys.argv[2]).resolve()
modules = {"opencv-python-headless": "cv2"}
bad = []
for dist in [*bounds, "lerobot", "metaworld", "mujoco", "torch", "pandas", "scipy"]:
    module = importlib.import_module(modules.get(dist, dist))
    where = "lower bound" if Path(module.__file__).resolve().is_relative_to(own) else "lock"
    version = md.version(dist)
    print(f"  {dist}=={version}  (imported {module.__name__} {getattr(module, '__version__', '')} from the {where})")
    if dist in bounds and (where != "lower bound" or version != bounds[dist]):
        bad.append(f"{dist}: {version} from the {where}, expected {bounds[dist]} from {own}")
if bad:
    sys.exit("[lower-bounds] not the versions asked for: " + "; ".join(bad))
PY
# Every installed distribution's requirements still hold (the lock's packages accept the lower bounds).
"$py" -I -m pip check

tests=(${SR_LB_TESTS:-tests/test_checked_files.py tests/test_progress.py tests/experiments/test_memory_budget.py tests/reporting
       tests/stream tests/envs tests/experiments/test_grid.py::test_a_grid_on_ray_gives_the_loops_results})
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 HF_HOME="$tmp/hf" MESA_SHADER_CACHE_DIR="$tmp/mesa"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
unset SR_TEST_OVERLAY PYTHONPATH
status=0
"$py" -m pytest -p no:xdist -p no:cacheprovider "${tests[@]}" "$@" || status=$?
[ "$(listing)" = "$before" ] || { echo "[lower-bounds] the shared venv's package list changed: $shared_site" >&2; exit 1; }
echo "[lower-bounds] pytest exit status $status, $(( $(date +%s) - started )) s in all" >&2
exit "$status"
