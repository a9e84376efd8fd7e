"""Closed-loop evaluation of the shared policy on learned skills (Section 4, "Evaluation protocol").

Each skill is evaluated with N episodes per evaluation seed (paper: N = 20, three evaluation seeds); an episode
succeeds when ``info["is_success"]`` becomes true (the environment terminates on success). The observation
trajectories (``agent_pos``, all 35 entries) are kept; SPI uses their ``SPI_FEATURES`` only (the report slices
them, ``sr_imitation.core.metrics.policy_motion``), and the first episodes of each skill can be saved as mp4 from
the scene camera (offscreen EGL). Episode e of evaluation seed s on the skill at stream position i always resets
with the same seed (``EVAL_SEED_OFFSET + 10000 s + 100 i + e``), whatever the stage: S[k, i] and S[i, i], and the
evaluation right after skill i's wake, are paired (common random numbers). Observations go through LeRobot's
``preprocess_observation`` and the policy's pre/post-processors, as in ``lerobot-eval``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from tqdm.auto import tqdm

from sr_imitation.video import write_mp4

logger = logging.getLogger(__name__)

EVAL_SEED_OFFSET = 1_000_000
"""Evaluation episodes use reset seeds far from the demonstration seeds."""

SPI_FEATURES: tuple[int, ...] = tuple(range(7))
"""Policy-dependent entries of the needle env's 35-d ``agent_pos`` used by SPI: the active arm's tool setpoint
``cur_x, cur_y, cur_z`` (cm), ``cur_roll, cur_pitch, cur_yaw`` (rad) and ``cur_jaw`` (``envs.needle.env.STATE_NAMES``
0-6). The rest is not the tool's own state or repeats it: ``goal_*`` (7-13) is set at reset, ``delta_*`` (14-20)
= goal - cur, ``achieved_*`` (21-27) repeats cur, ``desired_*`` (28-34) repeats goal (docs/NEEDLE_ENV.md)."""

NEEDLE_STATE_DIM = 35
"""Size of the needle env's ``agent_pos`` (``envs.needle.env.STATE_DIM``), the layout ``SPI_FEATURES`` refers to."""


def spi_features(state_dim: int) -> tuple[int, ...]:
    """The ``agent_pos`` entries SPI uses: ``SPI_FEATURES`` for the needle env's 35-d layout. Another environment
    (a custom ``EnvFactory``) has no declared layout here; all its entries are used, with a warning (our choice)."""
    if state_dim == NEEDLE_STATE_DIM:
        return SPI_FEATURES
    logger.warning("SPI: %d-d agent_pos is not the needle env's %d-d layout; using all %d entries", state_dim,
                   NEEDLE_STATE_DIM, state_dim)
    return tuple(range(state_dim))

EnvFactory = Callable[[str, bool], gym.Env]
"""(skill, with_scene_render) -> a gymnasium env with ``pixels``/``agent_pos`` observations."""


@dataclass
class EvalConfig:
    """Evaluation protocol.

    Each field is documented below (``--help`` shows it).
    """

    episodes: int = 20
    """Episodes per skill per evaluation seed (paper 20; 3 seeds x 20 = the paper's 60 per skill)."""
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    """Evaluation seeds (paper three); episodes reset identically at every stage."""
    max_steps: int = 300
    """Episode step limit (SurgicAI 300)."""
    videos_per_skill: int = 1
    """Episodes per skill (first seed) also saved as mp4; 0 disables videos."""
    video_height: int = 240
    """Video frame height."""
    video_width: int = 320
    """Video frame width."""
    thresholds: str = "learnable"
    """Success-threshold preset of the needle environment - learnable or surgicai."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or not self.seeds or self.max_steps < 1 or self.videos_per_skill < 0:
            raise ValueError("episodes, seeds, max_steps must be positive and videos_per_skill >= 0")


@dataclass
class SkillEvaluation:
    skill: str
    success_per_seed: list[float]
    episode_lengths: list[int]
    trajectories: list[np.ndarray]
    videos: list[str]

    @property
    def success(self) -> float:
        return float(np.mean(self.success_per_seed))


def needle_env_factory(image_size: tuple[int, int] | None, cfg: EvalConfig) -> EnvFactory:
    """Factory for the MuJoCo needle environment (imported lazily: it is a separate module)."""

    def make(skill: str, with_video: bool) -> gym.Env:
        from sr_imitation.envs.needle import gym_id

        kwargs: dict[str, Any] = {"thresholds": cfg.thresholds, "camera_dict": True}
        if image_size is None:
            kwargs["obs_type"] = "agent_pos"
        else:
            kwargs["image_height"], kwargs["image_width"] = image_size
        if with_video:
            kwargs.update(render_mode="rgb_array", render_height=cfg.video_height, render_width=cfg.video_width)
        return gym.make(gym_id(skill), max_episode_steps=cfg.max_steps, **kwargs)

    return make


def _to_policy_batch(obs: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Single-env observation -> LeRobot batch of size 1 (``pixels/<cam>`` -> ``observation.images.<cam>``)."""
    batched: dict[str, Any] = {}
    for key, value in obs.items():
        if isinstance(value, dict):
            batched[key] = {k: np.asarray(v)[None] for k, v in value.items()}
        else:
            batched[key] = np.asarray(value)[None]
    return preprocess_observation(batched)


def rollout(
    policy: Any, preprocessor: Any, postprocessor: Any, env: gym.Env, seed: int, max_steps: int, record: bool
) -> tuple[bool, int, np.ndarray, list[np.ndarray]]:
    """One episode; returns (success, steps, agent_pos trajectory (T x d), scene frames if ``record``)."""
    obs, info = env.reset(seed=seed)
    policy.reset()
    states, frames = [np.asarray(obs["agent_pos"], dtype=np.float64)], []
    if record:
        frames.append(env.render())
    success = bool(info.get("is_success", False))
    steps = 0
    while not success and steps < max_steps:
        with torch.no_grad():
            action = postprocessor(policy.select_action(preprocessor(_to_policy_batch(obs))))
        action = action.squeeze(0).cpu().numpy()
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
        states.append(np.asarray(obs["agent_pos"], dtype=np.float64))
        if record:
            frames.append(env.render())
        success = bool(info.get("is_success", False))
        if terminated or truncated:
            break
    return success, steps, np.stack(states), frames


def evaluate_skills(
    policy: Any,
    preprocessor: Any,
    postprocessor: Any,
    skills: Sequence[str],
    skill_indices: Sequence[int],
    make_env: EnvFactory,
    cfg: EvalConfig,
    video_dir: Path | None = None,
    progress: bool = True,
) -> dict[str, SkillEvaluation]:
    """Evaluate on every skill in ``skills`` (stream positions ``skill_indices``) over all evaluation seeds."""
    policy.eval()
    results: dict[str, SkillEvaluation] = {}
    total = len(skills) * len(cfg.seeds) * cfg.episodes
    bar = tqdm(total=total, desc="eval", disable=not progress, leave=False)
    for skill, index in zip(skills, skill_indices, strict=True):
        per_seed, lengths, trajectories, videos = [], [], [], []
        env = make_env(skill, False)
        video_env = make_env(skill, True) if video_dir is not None and cfg.videos_per_skill > 0 else None
        try:
            for s_i, eval_seed in enumerate(cfg.seeds):
                wins = 0
                for episode in range(cfg.episodes):
                    record = video_env is not None and s_i == 0 and episode < cfg.videos_per_skill
                    run_env = video_env if record else env
                    seed = EVAL_SEED_OFFSET + 10_000 * eval_seed + 100 * index + episode
                    ok, steps, states, frames = rollout(policy, preprocessor, postprocessor, run_env, seed,
                                                        cfg.max_steps, record)
                    wins += int(ok)
                    lengths.append(steps)
                    trajectories.append(states)
                    if record and frames:
                        path = Path(video_dir) / f"{skill}_episode{episode}_{'success' if ok else 'failure'}.mp4"
                        write_mp4(path, frames, fps=run_env.metadata.get("render_fps", 30))
                        videos.append(str(path))
                    bar.update(1)
                per_seed.append(wins / cfg.episodes)
        finally:
            env.close()
            if video_env is not None:
                video_env.close()
        results[skill] = SkillEvaluation(skill, per_seed, lengths, trajectories, videos)
        logger.info("eval %s: success %.3f per seed %s", skill, results[skill].success, per_seed)
    bar.close()
    return results
