"""README's stock LeRobot route run as written, with tiny budgets: ``sr-record``, ``lerobot-train
--policy.type=act_sr --policy.sleep=true`` on approach, a second ``lerobot-train --policy.path=<approach's checkpoint>``
on place, ``sr-sleep`` of both memories, stock ``lerobot-eval`` of the slept checkpoint (real subprocesses, in a
temporary folder).

Each command is README's own (read by tools/check_readme_routes.py's extractor), with :data:`TINY` appended: the same
flags again with smaller values (the last value of a repeated flag wins, in LeRobot's parser and in ours)."""

from __future__ import annotations

import hashlib
import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from lerobot.policies.factory import make_pre_post_processors

from lerobot_policy_act_sr import ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from lerobot_policy_act_sr.modeling_act_sr import MEMORY_FILE
from sr_imitation.core.memory import load_memory
from sr_imitation.substrates.act.substrate import normalize_raw_observations
from tests.tool_loader import load_tool

ROOT = Path(__file__).resolve().parents[3]
MARKER = "**The LeRobot workflow"
"""The line of README.md after which the stock route's ```bash block comes."""
_TRAIN = ["--steps=4", "--batch_size=4", "--save_freq=4", "--num_workers=0", "--env_eval_freq=0",
          "--wandb.enable=false", "--policy.device=cpu"]
TINY: list[list[str]] = [
    ["--num_episodes=2", "--image_size=32"],  # sr-record
    [*_TRAIN, "--policy.dim_model=32", "--policy.n_heads=2", "--policy.dim_feedforward=64",
     "--policy.n_encoder_layers=1", "--policy.chunk_size=8", "--policy.n_action_steps=8",
     "--policy.sleep_memory_size=8"],  # lerobot-train on approach
    _TRAIN,  # lerobot-train on place from --policy.path: the architecture and the memory size are the first run's
    ["--sleep.max_iterations=5", "--sleep.batch_size=4", "--progress=false"],  # sr-sleep
    ["--eval.n_episodes=1", "--eval.batch_size=1", "--env.episode_length=20", "--policy.device=cpu"],  # lerobot-eval
]
"""Appended to README's commands, in their order."""


def stock_route() -> list[list[str]]:
    """README's stock route, each command as its argv."""
    (block,) = load_tool("check_readme_routes").bash_blocks_after((ROOT / "README.md").read_text(), MARKER, 1)
    return [shlex.split(command) for command in block]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(argv: list[str], cwd: Path) -> None:
    exe = Path(sys.executable).parent / argv[0]
    proc = subprocess.run([str(exe), *argv[1:]], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, (argv[0], proc.stderr[-3000:])


@pytest.mark.slow
def test_readmes_stock_route_writes_each_skills_memory_and_sleeps_and_evaluates_both(tmp_path):
    """The second lerobot-train, started from the first's checkpoint with ``--policy.path``, writes place's memory in
    its own checkpoint and leaves approach's untouched; sr-sleep consolidates both; lerobot-eval loads the result."""
    route = stock_route()
    assert [argv[0] for argv in route] == ["sr-record", "lerobot-train", "lerobot-train", "sr-sleep", "lerobot-eval"]
    assert any(a.startswith("--policy.path=") for a in route[2])  # the second skill starts from the first's weights
    record, first, second, sleep, evaluate = (argv + tiny for argv, tiny in zip(route, TINY, strict=True))
    _run(record, tmp_path)
    _run(first, tmp_path)
    approach = tmp_path / "outputs" / "approach" / "checkpoints" / "last" / "pretrained_model"
    approach_digest = _digest(approach / MEMORY_FILE)
    _run(second, tmp_path)
    place = tmp_path / "outputs" / "place" / "checkpoints" / "last" / "pretrained_model"

    # Each checkpoint holds its own skill's memory; the first is carried on unchanged.
    assert _digest(approach / MEMORY_FILE) == approach_digest
    memories = {skill: load_memory(path / MEMORY_FILE, skill=f"local/sr_needle_{skill}")
                for skill, path in (("approach", approach), ("place", place))}
    assert all(isinstance(m, ActorMemory) and m.size == 8 for m in memories.values())  # 16 frames seen, 8 kept
    config = json.loads((place / "config.json").read_text())
    assert config["sleep"] is True and config["dim_model"] == 32  # the first run's policy, sleep on
    train_config = json.loads((place / "train_config.json").read_text())
    assert (tmp_path / train_config["policy"]["pretrained_path"]).resolve() == approach.resolve()  # as given
    # place's memory is the second run's final policy on place's observations
    policy = ACTSRPolicy.from_pretrained(place)
    pre, _ = make_pre_post_processors(policy.config, pretrained_path=str(place))
    assert memories["place"].verify_targets(
        lambda raw: policy.action_chunk(normalize_raw_observations(pre, raw)), atol=1e-5) <= 1e-5

    _run(sleep, tmp_path)
    slept = json.loads((tmp_path / "outputs" / "slept" / "sleep.json").read_text())
    assert [m["skill"] for m in slept["memories"]] == ["local/sr_needle_approach", "local/sr_needle_place"]
    assert slept["summed_loss"]["after"] < slept["summed_loss"]["before"]
    assert json.loads((tmp_path / "outputs" / "slept" / "pretrained_model" / "config.json").read_text())["sleep"]
    _run(evaluate, tmp_path)
    (info,) = (tmp_path / "outputs" / "eval").rglob("eval_info.json")
    assert not list(info.parent.rglob(MEMORY_FILE))  # lerobot-eval trains nothing and saves no memory
