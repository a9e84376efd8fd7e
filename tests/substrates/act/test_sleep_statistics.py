"""``sr-sleep`` on stock checkpoints whose statistics have a standard deviation of 0, and a sleep that fails.

The stock route: two ``lerobot-train --policy.type=act_sr --policy.sleep=true`` runs (approach, then place
fine-tuned from it) and ``sr-sleep``; place's jaw is constant (std 0), so approach's memory, re-expressed into
place's statistics, was divided by ~1e-8 (loss ~1e13, exit 0). Now those dimensions take the statistics of the
policy's and its memories' snapshots together, the policy is re-expressed with the same actions, and a sleep whose
losses are non-finite, absurd or do not move is one line naming the memory, a non-zero exit and nothing written.
``--eval.skills`` evaluates in every environment sr-train accepts (a gym id here).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors

from lerobot_policy_act_sr import ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from lerobot_policy_act_sr.modeling_act_sr import MEMORY_FILE
from sr_imitation.core.memory import load_memory
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.normalization import (
    floor_std,
    map_actions,
    pooled,
    reexpress_policy,
)
from sr_imitation.substrates.act.offline_sleep import (
    OfflineSleepConfig,
    PolicyPathConfig,
    SleepEvalConfig,
    SleepFailedError,
    load_policy,
    run_offline_sleep,
)
from sr_imitation.substrates.act.substrate import normalize_raw_observations
from tests.substrates.act.helpers import ACTION_DIM, STATE_DIM, make_skill_dataset, tiny_policy
from tests.substrates.act.test_offline_sleep import _loads_as_lerobot_eval_does, _one_line_error, _stock_checkpoint

JAW_ACTION, JAW_STATE = ACTION_DIM - 1, STATE_DIM - 1
QUICK = {"lr": 1e-3, "max_iterations": 5, "batch_size": 4, "early_stop_window": 5}


@pytest.fixture(scope="module")
def jaw_datasets(tmp_path_factory) -> Path:
    """approach (the jaw moves) and place (the jaw is held: std 0 in the action and the state)."""
    root = tmp_path_factory.mktemp("jaw")
    make_skill_dataset(root, "approach", 0)
    make_skill_dataset(root, "place", 1, constant={"action": {JAW_ACTION: 0.7}, "observation.state": {JAW_STATE: 0.3}})
    return root


@pytest.fixture(scope="module")
def stock(jaw_datasets, tmp_path_factory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp("stock")
    approach = _stock_checkpoint(jaw_datasets, "approach", out / "approach" / "pretrained_model")
    place = _stock_checkpoint(jaw_datasets, "place", out / "place" / "pretrained_model")
    return approach, place


def _config(place: Path, memories: list[Path], out: Path, **settings) -> OfflineSleepConfig:
    sleep = SurgicAISleepConfig(**{**QUICK, **settings.pop("sleep", {})})
    return OfflineSleepConfig(policy=PolicyPathConfig(path=place), memories=memories, sleep=sleep, output_dir=out,
                              progress=False, **settings)


# -- the statistics ------------------------------------------------------------------------------------------------
def test_reexpressing_keeps_the_policys_actions_and_the_floor_keeps_a_constant_dimension_constant():
    torch.manual_seed(0)
    from lerobot_policy_act_sr import ACTSRPolicy
    from tests.substrates.act.test_policy import _features

    policy = ACTSRPolicy(_features(tiny_policy(use_images=False), images=False)).eval()
    state, action = "observation.state", "action"
    old = {state: {"mean": torch.randn(STATE_DIM), "std": torch.rand(STATE_DIM) + 0.5},
           action: {"mean": torch.randn(ACTION_DIM), "std": torch.rand(ACTION_DIM) + 0.5}}
    old[action]["std"][JAW_ACTION] = 0.0  # a constant action dimension: the head outputs its mean, whatever it reads
    new = {state: {"mean": torch.randn(STATE_DIM), "std": torch.rand(STATE_DIM) + 0.5},
           action: {"mean": torch.randn(ACTION_DIM), "std": torch.rand(ACTION_DIM) + 0.5}}
    raw = torch.randn(5, STATE_DIM) * 2

    def actions(stats):
        x = (raw - stats[state]["mean"]) / (stats[state]["std"] + 1e-8)
        with torch.no_grad():
            y = policy.action_chunk({state: x, "observation.environment_state": x})
        return y * stats[action]["std"] + stats[action]["mean"]

    before = actions(old)
    reexpress_policy(policy, old, new)
    after = actions(new)
    assert torch.allclose(before, after, atol=1e-4), (before - after).abs().max()
    assert torch.allclose(after[..., JAW_ACTION], old[action]["mean"][JAW_ACTION].expand(5, 4), atol=1e-5)
    # The floor: a std of 0 becomes 0.01, the rest is untouched; a constant dimension still normalizes to 0.
    floored = floor_std({state: {"mean": torch.zeros(2), "std": torch.tensor([0.0, 3.0])}})
    assert floored[state]["std"].tolist() == [pytest.approx(0.01), 3.0]
    assert float((torch.tensor(0.0) - floored[state]["mean"][0]) / floored[state]["std"][0]) == 0.0
    together = pooled([{state: {"mean": torch.tensor([0.0]), "std": torch.tensor([0.0])}},
                       {state: {"mean": torch.tensor([2.0]), "std": torch.tensor([0.0])}}])
    assert together[state]["mean"].item() == 1.0 and together[state]["std"].item() == pytest.approx(1.0)
    targets = torch.randn(3, 4, ACTION_DIM)
    mapped = map_actions(targets, old[action], new[action])
    assert torch.allclose(mapped * new[action]["std"] + new[action]["mean"],
                          targets * old[action]["std"] + old[action]["mean"], atol=1e-5)


# -- the stock route with a constant jaw -----------------------------------------------------------------------------
def test_a_constant_jaw_in_the_deployed_statistics_gives_a_finite_sleep_that_lowers_the_losses(stock, tmp_path):
    approach, place = stock
    deployed = load_policy(place, "cpu").stats
    assert float(deployed["action"]["std"][JAW_ACTION]) < 1e-3  # the trap: LeRobot divides by ~0 + 1e-8 here
    record = run_offline_sleep(_config(place, [approach / MEMORY_FILE, place / MEMORY_FILE], tmp_path / "slept"))
    assert "standard deviation below 0.01 in observation.state[5], action[6]" in record["statistics"]
    losses = [(m["loss_before"], m["loss_after"]) for m in record["memories"]]
    assert all(np.isfinite(x) and x < 100 for pair in losses for x in pair), losses
    assert losses[1][0] < 1e-8  # place's memory is the deployed policy's own: re-expressing kept its actions
    assert record["summed_loss"]["after"] < record["summed_loss"]["before"]
    assert [m["targets"] for m in record["memories"]] == ["re-expressed", "re-expressed"]
    # The consolidated checkpoint is saved with the new statistics and loads as lerobot-eval loads it.
    _, policy, pre, post = _loads_as_lerobot_eval_does(tmp_path / "slept" / "pretrained_model")
    saved = load_policy(tmp_path / "slept" / "pretrained_model", "cpu").stats
    assert float(saved["action"]["std"][JAW_ACTION]) >= 0.01
    assert "Normalization statistics: standard deviation below" in (tmp_path / "slept" / "sleep.md").read_text()


def test_the_deployed_policys_actions_are_unchanged_by_the_new_statistics(stock, jaw_datasets):
    approach, place = stock
    from sr_imitation.substrates.act.offline_sleep import read_actor_memory, settle_statistics

    loaded = load_policy(place, "cpu")
    memory = load_memory(place / MEMORY_FILE)
    raw = {k: (v.float() / 255 if v.dtype == torch.uint8 else v) for k, v in memory.observations().items()}

    def acts():
        with torch.no_grad():
            return loaded.postprocessor(loaded.policy.action_chunk(loaded.preprocessor(dict(raw))))

    before = acts()
    read = [read_actor_memory(p / MEMORY_FILE, loaded) for p in (approach, place)]
    assert settle_statistics(loaded, [r.snapshot_stats for r in read], 0.01) is not None
    assert torch.allclose(acts(), before, atol=1e-4), (acts() - before).abs().max()


# -- a sleep that fails: one line naming the memory, non-zero exit, nothing written -------------------------------
_refused = _one_line_error  # sr-sleep's refusal: exit 2, one line


def test_absurd_nonfinite_or_unmoved_losses_are_one_line_naming_the_memory(stock, tmp_path, capsys):
    approach, place = stock
    memory = load_memory(approach / MEMORY_FILE)
    target = tmp_path / "slept"
    before = {p: p.stat().st_mtime_ns for p in place.iterdir()}

    def copy(name: str, targets: torch.Tensor) -> Path:
        path = approach.parent / f"{name}.safetensors"  # beside approach's checkpoint: its snapshot is found
        ActorMemory(memory.skill, {**memory.tensors, "target": targets}, dict(memory.config)).save(path)
        return path

    def args(memories: list[Path], *more: str) -> list[str]:
        return [f"--policy.path={place}", f"--memories=[{','.join(map(str, memories))}]", f"--output_dir={target}",
                "--progress=false", "--sleep.max_iterations=3", "--sleep.batch_size=4", "--sleep.early_stop_window=3",
                *more]

    huge = copy("huge", torch.full_like(memory.tensors["target"], 1e4))
    err = _refused(capsys, args([huge, place / MEMORY_FILE]))
    assert f"{huge}: memory loss" in err and "before the sleep is absurd" in err and "nothing was written" in err
    nan = copy("nan", torch.full_like(memory.tensors["target"], float("nan")))
    err = _refused(capsys, args([nan, place / MEMORY_FILE]))
    assert f"{nan}: memory loss nan before the sleep (non-finite)" in err
    err = _refused(capsys, args([approach / MEMORY_FILE, place / MEMORY_FILE], "--sleep.lr=1e-30"))
    assert f"{approach / MEMORY_FILE}: memory loss" in err and "the sleep changed nothing" in err
    assert not target.exists() and not any(p.name.startswith(".slept") for p in tmp_path.iterdir())
    assert {p: p.stat().st_mtime_ns for p in place.iterdir()} == before  # the input checkpoint is only read
    with pytest.raises(SleepFailedError):
        run_offline_sleep(_config(place, [huge], tmp_path / "other"))


# -- --eval.skills in another environment -----------------------------------------------------------------------------
class _TinyArm(gym.Env):
    """A gymnasium env with the tiny datasets' state and action (observation: the state, as agent_pos)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({"wrist": gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)})
        self.action_space = gym.spaces.Box(-1, 1, (ACTION_DIM,), np.float32)
        self.render_mode = render_mode
        self._state = np.zeros(STATE_DIM, np.float32)

    def _obs(self):
        return {"pixels": {"wrist": np.zeros((16, 16, 3), np.uint8)}, "agent_pos": self._state.copy()}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._state = self.np_random.normal(size=STATE_DIM).astype(np.float32)
        return self._obs(), {"is_success": False}

    def step(self, action):
        self._state = self._state + 0.1 * np.resize(np.asarray(action, np.float32), STATE_DIM)
        success = bool(self._state[0] > 1.0)
        return self._obs(), 0.0, success, False, {"is_success": success}

    def render(self):
        return np.zeros((16, 16, 3), np.uint8)


def test_eval_skills_in_a_gym_environment(stock, tmp_path):
    approach, place = stock
    gym.register(id="SrSleepTinyArm-v0", entry_point=_TinyArm)
    try:
        eval_cfg = SleepEvalConfig(skills=["pick", "place_cup"], env="gym",
                                   gym_ids=["SrSleepTinyArm-v0", "SrSleepTinyArm-v0"], episodes=1, seeds=[0],
                                   max_steps=3, videos_per_skill=0)
        record = run_offline_sleep(_config(place, [approach / MEMORY_FILE, place / MEMORY_FILE], tmp_path / "slept",
                                           eval=eval_cfg))
        assert set(record["success"]) == {"pick", "place_cup"}
        with pytest.raises(ValueError, match=r"eval.gym_ids\[1\] \(skill 'place_cup'\): gymnasium has no"):
            eval_cfg.gym_ids = ["SrSleepTinyArm-v0", "NoSuchArm-v0"]
            run_offline_sleep(_config(place, [place / MEMORY_FILE], tmp_path / "other", eval=eval_cfg))
        with pytest.raises(ValueError, match="eval.skills: \\['pick'\\] have no evaluation environment"):
            run_offline_sleep(_config(place, [place / MEMORY_FILE], tmp_path / "other",
                                      eval=SleepEvalConfig(skills=["pick"])))
    finally:
        gym.registry.pop("SrSleepTinyArm-v0", None)


# -- the stock route as a user runs it --------------------------------------------------------------------------------
@pytest.mark.slow
def test_the_stock_route_lerobot_train_twice_then_sr_sleep(jaw_datasets, tmp_path):
    """lerobot-train on approach (the README's ``--policy.sleep=true`` command: it writes the skill's memory beside the
    checkpoint), lerobot-train on place fine-tuned from it, sr-sleep (real subprocesses)."""
    bin_dir = Path(sys.executable).parent
    common = ["--policy.sleep=true", "--policy.sleep_memory_size=8", "--policy.push_to_hub=false",
              "--policy.device=cpu", "--dataset.video_backend=pyav", "--steps=4", "--batch_size=4",
              "--num_workers=0", "--env_eval_freq=0", "--save_freq=4", "--wandb.enable=false"]
    tiny = ["--policy.type=act_sr", "--policy.dim_model=32", "--policy.n_heads=2", "--policy.dim_feedforward=64",
            "--policy.n_encoder_layers=1", "--policy.n_vae_encoder_layers=1", "--policy.chunk_size=4",
            "--policy.n_action_steps=4"]

    def train(skill: str, *more: str) -> Path:
        out = tmp_path / skill
        proc = subprocess.run([str(bin_dir / "lerobot-train"), *more, *common,
                               f"--dataset.repo_id=local/sr_needle_{skill}", f"--dataset.root={jaw_datasets / skill}",
                               f"--output_dir={out}"], capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return out / "checkpoints" / "000004" / "pretrained_model"

    approach = train("approach", *tiny)
    config = json.loads((approach / "config.json").read_text())
    assert config["type"] == "act_sr" and any("images" in key for key in config["input_features"])  # the camera, used
    # by default (test_main_job.py's stock run gives --policy.use_images=false)
    # --policy.sleep=true on stock lerobot-train is accepted, and useful: the checkpoint's skill memory (a uniform
    # reservoir of the camera frames and states it trained on) is beside it
    memory = load_memory(approach / MEMORY_FILE, skill="local/sr_needle_approach")
    assert isinstance(memory, ActorMemory) and memory.size == 8  # 16 observations seen, 8 kept
    assert memory.observations()["observation.images.wrist"].dtype == torch.uint8
    loaded = ACTSRPolicy.from_pretrained(approach)
    assert loaded.config.sleep is True and loaded.config.sleep_memory_size == 8
    pre, _ = make_pre_post_processors(loaded.config, pretrained_path=str(approach))  # the checkpoint's own

    # the memory is this checkpoint's skill memory
    assert memory.verify_targets(lambda raw: loaded.action_chunk(normalize_raw_observations(pre, raw)),
                                 atol=1e-5) <= 1e-5
    place = train("place", f"--policy.path={approach}")
    proc = subprocess.run([str(bin_dir / "sr-sleep"), f"--policy.path={place}",
                           f"--memories=[{approach / MEMORY_FILE},{place / MEMORY_FILE}]",
                           f"--output_dir={tmp_path / 'slept'}", "--progress=false", "--sleep.max_iterations=5",
                           "--sleep.batch_size=4", "--sleep.lr=1e-3"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((tmp_path / "slept" / "sleep.json").read_text())
    losses = [(m["loss_before"], m["loss_after"]) for m in record["memories"]]
    assert all(np.isfinite(x) and x < 100 for pair in losses for x in pair), losses
    assert record["summed_loss"]["after"] < record["summed_loss"]["before"]
