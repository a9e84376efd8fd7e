#!/usr/bin/env bash
# Create (or reuse) the environments and print this clone's environment, <clone>/.venv, on the last line of stdout
# (its bin/ holds python, sr-*, lerobot-*, pytest, ruff, ...; `source <it>/bin/activate` to use it).
#
# Two layers, so that clones share the 8 GB of dependencies but never each other's code:
# - The dependency venv: the pinned third-party dependencies only, outside the clone, keyed by a hash of every file
#   that pins a dependency (~/.cache/sr_imitation/venv-<key>): a fresh machine builds it (about 8 GB, 2-3 minutes),
#   every later run and every clone with the same pins reuses it. Nothing of this project is installed there (an
#   older version of this script put it there: it is uninstalled).
# - The overlay: <clone>/.venv (git-ignored), a venv of its own on the same interpreter whose one .pth file adds the
#   dependency venv's site-packages behind its own. This clone's core and every plugin under policies/ are installed
#   into it in editable mode (the plugins are their own distributions so that LeRobot's `lerobot_policy_*` discovery
#   imports them; see docs/ARCHITECTURE.md), and every console script of the dependencies (lerobot-train,
#   lerobot-eval, pytest, ...) gets a wrapper there that runs the overlay's python, so that stock `lerobot-train`
#   finds this clone's act_sr. The overlay is rebuilt (seconds) when missing, or when the dependency venv, a
#   pyproject.toml or this script or .ci/overlay.py changed (stamp: .venv/.sr_overlay).
# SR_VENV=/path puts the dependency venv there instead (built there unless it holds a complete one; this project is
# never installed into it); the overlay is always <clone>/.venv. SR_PYTHON names the interpreter that builds it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
# The interpreter: SR_PYTHON if set, else the first Python 3.12 that runs among python3.12 on PATH (a pyenv shim
# fails unless a version is selected), pyenv's installed 3.12.x builds, and python3. Nothing is downloaded.
find_python() {
  local candidates=() c
  if [ -n "${SR_PYTHON:-}" ]; then candidates=("$SR_PYTHON"); else
    candidates=(python3.12)
    for c in "$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")"/versions/3.12.*/bin/python3.12; do candidates+=("$c"); done
    candidates+=(python3)
  fi
  for c in "${candidates[@]}"; do
    if "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' >/dev/null 2>&1; then echo "$c"; return 0; fi
  done
  echo "[venv] no Python 3.12 found (looked for ${candidates[*]}): install one (e.g. pyenv install 3.12) or set SR_PYTHON" >&2
  return 1
}
py="$(find_python)"
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
venv="$(mkdir -p "$(dirname "$venv")" && cd "$(dirname "$venv")" && pwd)/$(basename "$venv")"
# One build at a time: a second clone (or worktree) starting while the first builds waits here instead of deleting
# the half-built environment under it.
exec 9>"$venv.lock"
flock 9
if [ ! -f "$venv/.sr_complete" ]; then
  echo "[venv] building $venv (pins changed or first run)" >&2
  rm -rf "$venv"
  "$py" -m venv "$venv"
  # pip's index configuration on these machines prints one harmless warning per package: filter it.
  pip_quiet() { "$venv/bin/python" -m pip install --quiet "$@" 2>&1 | grep -v "is ignored: it is neither" >&2 || true; }
  pip_quiet --upgrade "pip==26.3" "setuptools==80.10.2" "wheel"
  # Dependencies of the core and of every plugin, resolved against the full lock (the core itself is removed
  # again by the purge below).
  pip_quiet -c .ci/constraints.txt ".[dev]"
  "$venv/bin/python" -c "import lerobot, metaworld, mujoco, torch, torchvision" \
    || { echo "[venv] dependency install failed" >&2; exit 1; }
  "$venv/bin/python" -I .ci/overlay.py purge "$venv" "$root"
  touch "$venv/.sr_complete"
else
  echo "[venv] reusing $venv" >&2
  "$venv/bin/python" -I .ci/overlay.py purge "$venv" "$root"
fi
flock -u 9
overlay="$root/.venv"
stamp="$key $venv $(stat -c %Y "$venv/.sr_complete") $root $(cat pyproject.toml policies/*/pyproject.toml .ci/venv.sh \
  .ci/overlay.py | sha256sum | cut -c1-16)"
if [ "$(cat "$overlay/.sr_overlay" 2>/dev/null || true)" != "$stamp" ]; then
  echo "[venv] building $overlay (this clone's code over $venv)" >&2
  rm -rf "$overlay"
  "$venv/bin/python" -I .ci/overlay.py create "$venv" "$overlay"
  plugins=()
  for d in policies/*/; do [ -f "$d/pyproject.toml" ] && plugins+=(-e "$d"); done
  # -P: the current directory (with the core's egg-info) is not on sys.path, so pip sees only the overlay's packages.
  PYTHONWARNINGS=ignore "$overlay/bin/python" -P -m pip install --quiet --no-deps --no-build-isolation --no-index \
    -e . "${plugins[@]}" >&2
  "$overlay/bin/python" -I .ci/overlay.py scripts "$overlay"
  echo "$stamp" >"$overlay/.sr_overlay"
else
  echo "[venv] reusing $overlay" >&2
fi
echo "$overlay"
