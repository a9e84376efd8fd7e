#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment and install the pinned dependencies, the core package
# and every LeRobot plugin under policies/. Prints the venv path on the last line of stdout.
#
# The environment lives outside the clone, keyed by a hash of every file that pins a dependency, so a fresh
# machine builds it from scratch (about 8 GB, 2-3 minutes) and later runs with the same pins reuse it. The
# project itself is always (re)installed in editable mode from *this* clone, so a reused venv never points
# at another checkout. Override the location with SR_VENV=/path.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
py="${SR_PYTHON:-python3.11}"
command -v "$py" >/dev/null 2>&1 || py=python3
# Key: the lock plus the dependency lists of every pyproject (not the whole file, so that adding a console
# script or a lint rule does not rebuild 8 GB).
key=$("$py" - <<'PY'
import glob, hashlib, json, tomllib
h = hashlib.sha256(open(".ci/constraints.txt", "rb").read())
for path in ["pyproject.toml", *sorted(glob.glob("policies/*/pyproject.toml"))]:
    project = tomllib.load(open(path, "rb"))["project"]
    h.update(json.dumps([path, project.get("dependencies"), project.get("optional-dependencies")]).encode())
print(h.hexdigest()[:16])
PY
)
venv="${SR_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/sr_imitation/venv-$key}"
if [ ! -f "$venv/.sr_complete" ]; then
  echo "[venv] building $venv (pins changed or first run)" >&2
  rm -rf "$venv"
  mkdir -p "$(dirname "$venv")"
  "$py" -m venv "$venv"
  # pip's index configuration on these machines prints one harmless warning per package: filter it.
  pip_quiet() { "$venv/bin/python" -m pip install --quiet "$@" 2>&1 | grep -v "is ignored: it is neither" >&2 || true; }
  pip_quiet --upgrade "pip==26.3" "setuptools==80.10.2" "wheel"
  # Dependencies of the core and of every plugin, resolved against the full lock.
  pip_quiet -c .ci/constraints.txt ".[dev]"
  "$venv/bin/python" -c "import lerobot, metaworld, mujoco, torch, torchvision" \
    || { echo "[venv] dependency install failed" >&2; exit 1; }
  "$venv/bin/python" -m pip uninstall --quiet -y sr_imitation >&2
  touch "$venv/.sr_complete"
else
  echo "[venv] reusing $venv" >&2
fi
# Editable installs of this clone: the core and every plugin (plugins are their own distributions so that
# LeRobot's `lerobot_policy_*` discovery imports them; see docs/ARCHITECTURE.md).
plugins=()
for d in policies/*/; do [ -f "$d/pyproject.toml" ] && plugins+=(-e "$d"); done
"$venv/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e . "${plugins[@]}" >&2
echo "$venv"
