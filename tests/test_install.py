"""Installation: each clone runs its own code over the shared dependency venv, the package installs into an
existing LeRobot environment with plain pip (see .ci/venv.sh, .ci/overlay.py and the README's "Install"), and its
direct dependencies are ranges that hold the lock and start at the tested lower bounds (.ci/lower_bounds.txt)."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
OVERLAY_PY = ROOT / ".ci" / "overlay.py"
PTH_NAME = "sr_shared_deps.pth"  # .ci/overlay.py's PTH_NAME
PROJECT_DISTS = {"sr_imitation", "lerobot_policy_act_sr", "lerobot_env_sr"}


def _is_relative_to(path: str | Path, parent: Path) -> bool:
    return Path(path).resolve().is_relative_to(parent.resolve())


@pytest.fixture(scope="module")
def shared_site() -> Path:
    """The shared dependency site-packages that this interpreter's overlay (<repo>/.venv) reaches. Skips when the
    tests do not run under the overlay layout (e.g. a plain PYTHONPATH run on the dependency venv's python); fails
    instead under .ci/test.sh, which sets SR_TEST_OVERLAY."""
    overlay = ROOT / ".venv"
    pth = Path(overlay / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
               / PTH_NAME)
    reason = None
    if Path(sys.prefix).resolve() != overlay.resolve():
        reason = f"the interpreter's prefix is {sys.prefix}, not this checkout's overlay {overlay} (.ci/venv.sh)"
    elif not pth.is_file():
        reason = f"{pth} is missing: {overlay} is not an overlay made by .ci/venv.sh"
    if reason is not None:
        if os.environ.get("SR_TEST_OVERLAY"):
            pytest.fail(f"SR_TEST_OVERLAY is set but {reason}")
        pytest.skip(f"not running under the overlay layout: {reason}")
    out = subprocess.run([sys.executable, "-I", str(OVERLAY_PY), "shared-site", str(overlay)], check=True,
                         capture_output=True, text=True).stdout.strip()
    site = Path(out)
    assert site.is_dir() and (site.parents[2] / ".sr_complete").is_file(), f"{site}: not a complete dependency venv"
    return site


def _clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env.update(OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", **extra)
    return env


def _copy_checkout(dest: Path) -> Path:
    """A second copy of this checkout as a clone's working tree holds it: the tracked files and the untracked ones
    that git does not ignore (so uncommitted work is included), not the ignored build outputs or .venv."""
    listed = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            check=True, capture_output=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src = ROOT / rel
        if src.is_file():  # a deleted (or meanwhile removed) file is not in the working tree
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def _fingerprint(tree: Path) -> str:
    """Hash of every file and link under ``tree`` (paths, contents, link targets), byte-code caches left out."""
    h = hashlib.sha256()
    for path in sorted(tree.rglob("*")):
        if "__pycache__" in path.parts:
            continue
        h.update(str(path.relative_to(tree)).encode())
        if path.is_symlink():
            h.update(os.readlink(path).encode())
        elif path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()


_PROBE = (
    "import importlib.metadata as m, json, sys\n"
    "from lerobot.utils.import_utils import register_third_party_plugins\n"
    "register_third_party_plugins()\n"
    "import lerobot_policy_act_sr, sr_imitation\n"
    "from lerobot.policies.factory import make_policy_config\n"
    "from lerobot.envs.configs import EnvConfig\n"
    "config = make_policy_config('act_sr')\n"
    "print(json.dumps({'sr_imitation': sr_imitation.__file__, 'plugin': lerobot_policy_act_sr.__file__,\n"
    "                  'config': type(config).__module__ + '.' + type(config).__name__,\n"
    "                  'envs': sorted({'needle', 'sr_meta_world'} & set(EnvConfig.get_known_choices())),\n"
    "                  'dists': {n: str(m.distribution(n).locate_file('')) for n in"
    " ('sr_imitation', 'lerobot_policy_act_sr', 'lerobot_env_sr')}}))\n"
)
"""Run in a fresh interpreter from a neutral directory: where LeRobot's plugin discovery finds the project."""


def _probe(python: Path, cwd: Path) -> dict:
    proc = subprocess.run([str(python), "-c", _PROBE], cwd=cwd, env=_clean_env(), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_this_interpreter_runs_this_checkout_and_the_shared_venv_holds_no_project_code(shared_site):
    import lerobot_policy_act_sr
    import sr_imitation

    assert _is_relative_to(sr_imitation.__file__, ROOT), sr_imitation.__file__
    assert _is_relative_to(lerobot_policy_act_sr.__file__, ROOT / "policies"), lerobot_policy_act_sr.__file__
    own_site = Path(sys.prefix) / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    in_own = {d.metadata["Name"] for d in importlib.metadata.distributions(path=[str(own_site)])}
    assert in_own >= PROJECT_DISTS, in_own  # installed (editable) in this clone's overlay, not in the shared venv
    in_shared = {d.metadata["Name"] for d in importlib.metadata.distributions(path=[str(shared_site)])}
    assert "lerobot" in in_shared and not (PROJECT_DISTS & in_shared), PROJECT_DISTS & in_shared
    assert not list(shared_site.glob("__editable__*")), "an editable install left in the shared venv"
    # The overlay's own packages come first on sys.path, the shared dependencies after them.
    paths = [Path(p).resolve() for p in sys.path if p]
    assert paths.index(own_site.resolve()) < paths.index(shared_site.resolve())
    # lerobot-train next to this interpreter runs this interpreter (so it finds this clone's plugin).
    first = (Path(sys.executable).parent / "lerobot-train").read_text().splitlines()[0]
    assert first == f"#!{Path(sys.executable).parent / 'python'}", first


@pytest.mark.slow
def test_two_clones_each_run_their_own_code_over_one_shared_venv(shared_site, tmp_path):
    first_overlay = ROOT / ".venv"
    before = _fingerprint(first_overlay)
    clone = _copy_checkout(tmp_path / "clone")
    shared_venv = shared_site.parents[2]
    proc = subprocess.run(["bash", str(clone / ".ci" / "venv.sh")], cwd=tmp_path, capture_output=True, text=True,
                          env=_clean_env(SR_VENV=str(shared_venv)), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == str(clone / ".venv"), proc.stdout
    assert f"reusing {shared_venv}" in proc.stderr, proc.stderr  # the same shared venv, not rebuilt
    neutral = tmp_path / "elsewhere"
    neutral.mkdir()
    for root in (ROOT, clone):
        found = _probe(root / ".venv" / "bin" / "python", neutral)
        assert _is_relative_to(found["sr_imitation"], root / "sr_imitation"), (root, found)
        assert _is_relative_to(found["plugin"], root / "policies" / "lerobot_policy_act_sr"), (root, found)
        assert all(_is_relative_to(loc, root / ".venv") for loc in found["dists"].values()), (root, found)
        assert found["config"] == "lerobot_policy_act_sr.configuration_act_sr.ACTSRConfig", found
        assert found["envs"] == ["needle", "sr_meta_world"], found  # by LeRobot's lerobot_env_* discovery
        for script in ("lerobot-train", "lerobot-eval", "sr-train", "sr-sleep"):
            first = (root / ".venv" / "bin" / script).read_text().splitlines()[0]
            assert first == f"#!{root / '.venv' / 'bin' / 'python'}", (script, first)
    # Building the second clone's overlay left the first one's as it was, and put nothing into the shared venv.
    assert _fingerprint(first_overlay) == before
    assert not (PROJECT_DISTS & {d.metadata["Name"] for d in importlib.metadata.distributions(path=[str(shared_site)])})


@pytest.mark.slow
def test_pip_install_into_an_existing_lerobot_environment(shared_site, tmp_path):
    """The README's route for LeRobot users: plain (non-editable) pip installs of the repository and its plugin into
    an environment that already has LeRobot 0.6 (here: a fresh overlay of the shared dependencies, which holds no
    project code), without network; then LeRobot's factory makes act_sr and stock lerobot-train runs there."""
    src = _copy_checkout(tmp_path / "src")
    env_dir = tmp_path / "lerobot_env"
    shared_python = shared_site.parents[2] / "bin" / "python"
    subprocess.run([str(shared_python), "-I", str(OVERLAY_PY), "create", str(shared_site.parents[2]), str(env_dir)],
                   check=True, timeout=120)
    subprocess.run([str(env_dir / "bin" / "python"), "-I", str(OVERLAY_PY), "scripts", str(env_dir)], check=True,
                   timeout=120)  # the existing environment's lerobot-* commands
    python = env_dir / "bin" / "python"
    without = subprocess.run([str(python), "-c", "import sr_imitation"], cwd=tmp_path, env=_clean_env(),
                             capture_output=True, text=True)
    assert without.returncode != 0, "the fresh LeRobot environment already imports sr_imitation"
    proc = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--no-index", "--no-build-isolation",
                           "--no-cache-dir", str(src), str(src / "policies" / "lerobot_policy_act_sr"),
                           str(src / "policies" / "lerobot_env_sr")],
                          cwd=tmp_path, env=_clean_env(PYTHONWARNINGS="ignore"), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    check = subprocess.run([str(python), "-m", "pip", "check"], cwd=tmp_path, env=_clean_env(PYTHONWARNINGS="ignore"),
                           capture_output=True, text=True, timeout=300)
    assert check.returncode == 0 and "No broken requirements found" in check.stdout, check.stdout + check.stderr
    site = env_dir / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    found = _probe(python, tmp_path)
    assert _is_relative_to(found["sr_imitation"], site) and _is_relative_to(found["plugin"], site), found
    assert found["config"] == "lerobot_policy_act_sr.configuration_act_sr.ACTSRConfig", found
    assert found["envs"] == ["needle", "sr_meta_world"], found
    assert (env_dir / "bin" / "sr-train").is_file()  # the package's own commands came with it
    help_ = subprocess.run([str(env_dir / "bin" / "lerobot-train"), "--help"], cwd=tmp_path, env=_clean_env(),
                           capture_output=True, text=True, timeout=300)
    assert help_.returncode == 0, help_.stderr[-3000:]
    assert "act_sr" in help_.stdout  # among --policy.type's choices
    # The shared dependency venv is untouched by the user's install.
    assert not (PROJECT_DISTS & {d.metadata["Name"] for d in importlib.metadata.distributions(path=[str(shared_site)])})


EXACT_PINS = {"metaworld", "mujoco"}
"""The only exact direct dependencies (pyproject.toml says why); every other one is a range."""


def _pins(path: Path) -> dict[str, Version]:
    """The ``name==version`` lines of a lock file (comments and blank lines skipped), by canonical name."""
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier
            assert spec.operator == "==", f"{path.name}: {line!r} is not name==version"
            pins[canonicalize_name(req.name)] = Version(spec.version)
    return pins


def _direct_dependencies() -> list[Requirement]:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return [Requirement(d) for d in tomllib.load(f)["project"]["dependencies"]]


def test_direct_dependencies_are_ranges_that_hold_the_lock_and_start_at_the_tested_lower_bounds():
    deps = _direct_dependencies()
    lock, lower = _pins(ROOT / ".ci" / "constraints.txt"), _pins(ROOT / ".ci" / "lower_bounds.txt")
    names = {canonicalize_name(r.name) for r in deps}
    assert names >= EXACT_PINS and set(lower) == names - EXACT_PINS, (sorted(names), sorted(lower))
    for req in deps:
        name = canonicalize_name(req.name)
        assert name in lock and req.specifier.contains(lock[name]), f"{req}: the lock's {lock.get(name)} lies outside"
        ops = {s.operator: Version(s.version) for s in req.specifier}
        if name in EXACT_PINS:
            assert list(ops) == ["=="], f"{req}: exact pin expected"
            continue
        # a range: from the tested lower bound (tools/check_lower_bounds.sh) to an upper bound, nothing pinned
        assert set(ops) == {">=", "<"} and len(req.specifier) == 2, f"{req}: expected >=LOW,<UPPER"
        assert ops[">="] == lower[name], f"{req}: .ci/lower_bounds.txt records {lower[name]} as tested"
        assert ops[">="] < ops["<"], str(req)


def test_the_ranges_lie_inside_the_pinned_lerobot_s_own():
    lerobot = {canonicalize_name(r.name): r.specifier for r in map(Requirement, importlib.metadata.requires("lerobot"))
               if r.marker is None}
    deps = _direct_dependencies()
    for req in deps:
        theirs = lerobot.get(canonicalize_name(req.name))
        if theirs is None or canonicalize_name(req.name) in EXACT_PINS:
            continue
        ours = {s.operator: Version(s.version) for s in req.specifier}
        assert theirs.contains(ours[">="]), f"{req}: its lower bound is outside LeRobot's {theirs}"
        uppers = [Version(s.version) for s in theirs if s.operator == "<"]
        assert all(ours["<"] <= u for u in uppers), f"{req}: its upper bound is above LeRobot's {theirs}"
