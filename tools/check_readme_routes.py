"""Run README's stock LeRobot route and its own-skills commands as written, on a fresh clone, headless.

    python3 tools/check_readme_routes.py [--work DIR] [--ref REF] [--resume]

What it does, in order (every step logged with its wall time; exit 0 only if every command exits 0):
1. ``git clone`` of this repository at REF (default HEAD) into ``<work>/clone`` and ``bash .ci/venv.sh`` there (the
   README's set-up); the clone's ``.venv/bin`` goes first on PATH, as an activated environment would.
2. The stock route: the first ```bash block after README's "**The LeRobot workflow" line, each command exactly as
   written (continuation lines joined, comments dropped), in the clone, with ``MUJOCO_GL``, ``PYOPENGL_PLATFORM`` and
   ``DISPLAY`` unset (headless, as on a server).
3. What the own-skills commands expect a user to have, made here and nowhere else: two small camera datasets
   (``sr-record --video=true``, 4 episodes of the needle's approach and place) under the names the README uses
   (``$HF_LEROBOT_HOME/user/pick``, ``user/place_cup``, ``data/pick``, ``data/place_cup``), and a package ``my_pkg``
   on PYTHONPATH that registers ``Pick-v0`` / ``PlaceCup-v0`` (the needle's approach and place) as a user's would.
4. The own-skills commands: the two ``sr-train`` lines of the block after "Your own skills.", then the
   ``sr-grid`` / ``hypotheses`` block after "Does sleep help on your skills?" (docs/COMMANDS.md) with
   ``my_skills.json`` = the gym run's ``train_config.json``
   (the README's own suggestion: "a finished run's train_config.json"). These are the README's commands with one
   change, said here and in the log: each ``sr-train`` line gets :data:`BUDGET` appended (the paper's wake budget,
   100 epochs of LeRobot's 40M-parameter ACT, is hours a skill on a CPU); the grid inherits it through the config.

Nothing here is a test of numbers: it checks that a user who copies the commands gets through, headless, and how
long each command takes (docs/BENCHMARKS.md records a run).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUDGET = "--wake.max_epochs=2 --wake.min_epochs=1 --wake.max_steps_per_epoch=3 --sleep.max_iterations=10"
"""Appended to the own-skills ``sr-train`` lines only (the change from the README, stated in the log)."""
EVAL_BUDGET = "--eval.episodes=2 --eval.seeds=[0] --eval.max_steps=100 --eval.videos_per_skill=0"
"""Appended besides :data:`BUDGET` to the lines that evaluate (not ``--eval.env=none``)."""
HEADLESS_UNSET = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")
MY_PKG = '''"""A user's package registering their skills' environments (here: the needle's approach and place, its wrist
camera named as the datasets name it, LeRobot's gym convention: pixels={"wrist": image} -> observation.images.wrist)."""
import gymnasium as gym

for _id, _skill in (("Pick-v0", "approach"), ("PlaceCup-v0", "place")):
    if f"my_pkg/{_id}" not in gym.registry:
        gym.register(id=f"my_pkg/{_id}", entry_point="sr_imitation.envs.needle.env:NeedleEnv",
                     max_episode_steps=300, kwargs={"skill": _skill, "camera_dict": True})
'''


def log(message: str) -> None:
    sys.stdout.write(f"[{time.strftime('%H:%M:%S')}] {message}\n")
    sys.stdout.flush()


def bash_blocks_after(readme: str, marker: str, count: int) -> list[list[str]]:
    """The first ``count`` ```bash blocks after the line holding ``marker``, each as its commands (continuations
    joined, comments and blank lines dropped)."""
    start = readme.index(marker)
    blocks = re.findall(r"```bash\n(.*?)```", readme[start:], flags=re.S)[:count]
    if len(blocks) < count:
        raise SystemExit(f"README.md: fewer than {count} bash blocks after {marker!r}")
    out = []
    for block in blocks:
        joined = re.sub(r"\\\n\s*", " ", block)
        commands = []
        for line in joined.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line and not line.startswith("#"):
                commands.append(line)
        out.append(commands)
    return out


class Runner:
    """Runs each command in the clone and records its time in ``record`` (``times.json``, rewritten after every
    command, so a failed try leaves what ``--resume`` reads); with ``done``, a command that already exited 0 there,
    with the same text, is skipped (its earlier time kept)."""

    def __init__(self, clone: Path, env: dict[str, str], record: Path, commit: str,
                 done: dict[str, dict] | None = None) -> None:
        self.clone, self.env, self.record, self.commit = clone, env, record, commit
        self.times: list[dict] = []
        self.done = done or {}

    def __call__(self, command: str, note: str = "") -> None:
        if command in self.done:
            log(f"$ {command}\n  done before (rc=0 in {self.done[command]['seconds']} s): skipped (--resume)")
            self.times.append({**self.done[command], "resumed": True})
            self._save()
            return
        log(f"$ {command}" + (f"    # {note}" if note else ""))
        t0 = time.perf_counter()
        proc = subprocess.run(["bash", "-c", command], cwd=self.clone, env=self.env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        seconds = time.perf_counter() - t0
        tail = "\n".join(proc.stdout.rstrip().splitlines()[-8:])
        self.times.append({"command": command, "seconds": round(seconds, 1), "rc": proc.returncode, "note": note})
        log(f"  rc={proc.returncode} in {seconds:.1f} s; last lines:\n{tail}")
        self._save()
        if proc.returncode != 0:
            raise SystemExit(f"failed: {command}")

    def _save(self) -> None:
        self.record.write_text(json.dumps({"commit": self.commit, "commands": self.times}, indent=2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    parser.add_argument("--ref", default="HEAD", help="the commit to clone (default HEAD)")
    parser.add_argument("--resume", action="store_true",
                        help="keep <work>/clone and its outputs, check out REF there, skip the commands that already "
                             "exited 0 (after a README fix: the rest of the route runs as the new README writes it)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="sr_readme_routes."))
    work.mkdir(parents=True, exist_ok=True)
    clone = work / "clone"
    commit = subprocess.check_output(["git", "-C", str(ROOT), "rev-parse", args.ref], text=True).strip()
    log(f"work folder {work}; commit {commit}")
    done: dict[str, dict] = {}
    if args.resume and clone.exists():
        subprocess.run(["git", "-C", str(clone), "fetch", "-q", str(ROOT), commit], check=True)
        previous = json.loads((work / "times.json").read_text())["commands"] if (work / "times.json").exists() else []
        done = {c["command"]: c for c in previous if c["rc"] == 0}
    else:
        if clone.exists():
            shutil.rmtree(clone)
        subprocess.run(["git", "clone", "-q", "--no-checkout", str(ROOT), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "-q", commit], check=True)
    t0 = time.perf_counter()
    venv = subprocess.run(["bash", ".ci/venv.sh"], cwd=clone, check=True, stdout=subprocess.PIPE,
                          text=True).stdout.strip().splitlines()[-1]
    log(f"set-up (bash .ci/venv.sh): {time.perf_counter() - t0:.1f} s, environment {venv}")

    env = {k: v for k, v in os.environ.items() if k not in HEADLESS_UNSET}
    env["PATH"] = f"{clone / '.venv' / 'bin'}:{venv}/bin:{env['PATH']}"
    env["HF_LEROBOT_HOME"] = str(work / "hf_lerobot")
    env["PYTHONPATH"] = str(work / "user_pkgs")
    run = Runner(clone, env, work / "times.json", commit, done)
    readme = (clone / "README.md").read_text()

    (stock,) = bash_blocks_after(readme, "**The LeRobot workflow", 1)
    log(f"stock route: {len(stock)} commands from README.md")
    for command in stock:
        run(command)

    # what a user of the own-skills section has: camera datasets of their own, and their envs' package
    user_data = work / "user_data"
    run(f"sr-record --skills=[approach,place] --num_episodes=4 --video=true --root={user_data}",
        "fixture: the user's own camera datasets")
    for name, skill in (("pick", "approach"), ("place_cup", "place")):
        shutil.copytree(user_data / skill, work / "hf_lerobot" / "user" / name, dirs_exist_ok=True)
        shutil.copytree(user_data / skill, clone / "data" / name, dirs_exist_ok=True)
    (work / "user_pkgs" / "my_pkg").mkdir(parents=True, exist_ok=True)
    (work / "user_pkgs" / "my_pkg" / "__init__.py").write_text(MY_PKG)

    (own_train,) = bash_blocks_after(readme, "**Your own skills.**", 1)
    commands_page = (clone / "docs" / "COMMANDS.md").read_text()  # README links there for the grid and its test
    (grid,) = bash_blocks_after(commands_page, "**Does sleep help on your skills?**", 1)
    for command in own_train:
        extra = BUDGET if "--eval.env=none" in command else f"{BUDGET} {EVAL_BUDGET}"
        run(f"{command} {extra}", "README's command + the CPU budget flags")
    shutil.copyfile(clone / "outputs" / "mine_gym" / "train_config.json", clone / "my_skills.json")
    for command in grid:
        run(command, "my_skills.json = outputs/mine_gym/train_config.json")

    log(f"every command exited 0; times in {run.record}")


if __name__ == "__main__":
    sys.exit(main())
