"""Rollout evaluation on Meta-World skills (Appendix A.1, "Evaluation protocol").

The same harness scores our SAC actor, Meta-World's own scripted policies (``metaworld.policies``) and a random
policy, which is how it is checked against code nobody here wrote: the scripted policies must reach >= 0.9
success on every MT5 skill and the random policy stays near 0 (``tests/substrates/sac/test_envs_evaluate.py``,
``docs/BENCHMARKS.md``).

Success: ``any_step`` (the episode succeeds if Meta-World reports success at any step, the Continual World /
Meta-World convention) or ``final_step`` (success at the last step). With ``any_step`` an episode may stop at the
first success (``stop_on_success``) without changing the success rate.

Paired evaluation (common random numbers): :func:`evaluation_configurations` gives the configuration indices of a
skill's N evaluation episodes from (run seed, skill identity, episode) only, so the stream trainer evaluates skill
i on the same configurations after its wake and after every stage; S[k, i] - S[i, i] then compares the same
episodes (our choice; the paper does not say how its evaluation configurations are drawn).

SPI: only the robot's own state enters (``SPI_FEATURES``, :func:`sr_imitation.core.metrics.policy_motion`).

Videos: with a :class:`~sr_imitation.envs.metaworld.video.VideoSpec` the first ``spec.episodes`` episodes are also
rendered offscreen (the frame after reset, then one per step) into ``<skill>_episode<i>_<success|failure>.mp4``.
Rendering only reads the simulation state, so the outcome is identical with and without videos
(``tests/substrates/sac/test_video.py``).
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sr_imitation.envs.metaworld.tasks import ACT_DIM, NUM_CONFIGURATIONS, SkillEnv, canonical_skill
from sr_imitation.envs.metaworld.video import SkillRenderer, VideoSpec, VideoWriter

logger = logging.getLogger(__name__)

ActFn = Callable[[np.ndarray], np.ndarray]
"""A policy as a function of one 39-d observation returning one 4-d action."""

SUCCESS_MODES = ("any_step", "final_step")

SPI_FEATURES: tuple[int, ...] = (0, 1, 2, 3)
"""Policy-dependent entries of the 39-d Meta-World v3 observation used by SPI: the end-effector position (xyz, m,
``obs[0:3]``) and the gripper opening (finger distance / 0.1 m clipped to [0, 1], ``obs[3]``). The rest is not the
robot's own state: ``obs[4:18]`` object positions and quaternions, ``obs[18:36]`` the previous frame of
``obs[0:18]``, ``obs[36:39]`` the goal (``SawyerXYZEnv._get_obs`` in Meta-World 3.1.1)."""

EVAL_SEED_SALT = 0x5E1F_E7A1
"""Separates the evaluation configuration stream from every training seed derived from the run seed."""


def evaluation_configurations(run_seed: int, skill: str, episodes: int) -> list[int]:
    """Configuration indices (0..49) of the ``episodes`` evaluation episodes of ``skill``: drawn uniformly (with
    replacement, as the uniform protocol samples) from a generator seeded by (run seed, skill identity), so episode
    j gets the same configuration at every stage and in every evaluation of that run (common random numbers). The
    skill enters by its canonical name (CRC-32), not its stream position: the same skill is paired across stream
    orders too.

    Raises:
        ValueError: ``episodes`` < 1.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    key = zlib.crc32(canonical_skill(skill).encode())
    rng = np.random.default_rng(np.random.SeedSequence([int(run_seed), EVAL_SEED_SALT, key]))
    return [int(x) for x in rng.integers(NUM_CONFIGURATIONS, size=episodes)]


@dataclass
class EvalResult:
    """Outcome of ``episodes`` rollouts on one skill."""

    skill: str
    successes: list[bool]
    returns: list[float]
    lengths: list[int]
    trajectories: list[np.ndarray] = field(default_factory=list, repr=False)
    videos: list[Path] = field(default_factory=list)
    """mp4 files of the recorded episodes (episode order)."""

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else float("nan")

    def summary(self) -> dict[str, float | int | str]:
        return {
            "skill": self.skill,
            "episodes": len(self.successes),
            "success_rate": self.success_rate,
            "mean_return": float(np.mean(self.returns)) if self.returns else float("nan"),
            "mean_length": float(np.mean(self.lengths)) if self.lengths else float("nan"),
        }


def evaluate_policy(
    act: ActFn,
    env: SkillEnv,
    episodes: int,
    seed: int,
    success_mode: str = "any_step",
    stop_on_success: bool = True,
    record_trajectories: bool = False,
    configurations: Sequence[int] | None = None,
    video: VideoSpec | None = None,
) -> EvalResult:
    """Roll out ``act`` for ``episodes`` episodes on ``env`` (configurations drawn from ``seed``).

    Args:
        act: policy, observation -> action in [-1, 1]^4.
        env: the skill environment (reseeded here with ``seed``).
        episodes: number of evaluation episodes N (paper: 100).
        seed: evaluation seed (configurations per episode).
        success_mode: ``any_step`` or ``final_step``.
        stop_on_success: end an episode at its first success (``any_step`` only).
        record_trajectories: keep each episode's observations (T x 39); SPI uses their ``SPI_FEATURES``.
        configurations: evaluate exactly these configuration indices, one episode each, instead of sampling
            (``range(50)`` gives the population success rate of the uniform protocol).
        video: record the first ``video.episodes`` episodes as mp4 into ``video.directory`` (None: no videos).
    """
    if configurations is not None:
        episodes = len(configurations)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if success_mode not in SUCCESS_MODES:
        raise ValueError(f"success_mode must be one of {SUCCESS_MODES}, got {success_mode!r}")
    stop_early = stop_on_success and success_mode == "any_step"
    env.seed(seed)
    result = EvalResult(env.skill, [], [], [])
    n_videos = min(video.episodes, episodes) if video is not None else 0
    renderer = SkillRenderer(env, video.height, video.width, video.camera) if video is not None and n_videos else None
    try:
        for episode in range(episodes):
            configuration = None if configurations is None else int(configurations[episode])
            if video is not None and renderer is not None and episode < n_videos:
                with VideoWriter(video.directory, f"{canonical_skill(env.skill)}_episode{episode}", env.fps) as w:
                    success, total, length, observations = _rollout(
                        act, env, configuration, success_mode, stop_early, record_trajectories,
                        on_frame=lambda w=w: w.append(renderer.frame()))
                    result.videos.append(w.finish("success" if success else "failure"))
            else:
                success, total, length, observations = _rollout(
                    act, env, configuration, success_mode, stop_early, record_trajectories)
            result.successes.append(success)
            result.returns.append(total)
            result.lengths.append(length)
            if record_trajectories:
                result.trajectories.append(np.stack(observations).astype(np.float32))
    finally:
        if renderer is not None:
            renderer.close()
    logger.info("eval %s: success %.3f over %d episodes%s", env.skill, result.success_rate, episodes,
                f", {len(result.videos)} video(s) in {video.directory}" if video is not None and n_videos else "")
    return result


def _rollout(
    act: ActFn,
    env: SkillEnv,
    configuration: int | None,
    success_mode: str,
    stop_early: bool,
    keep_observations: bool,
    on_frame: Callable[[], None] | None = None,
) -> tuple[bool, float, int, list[np.ndarray]]:
    """One episode: (success, return, length, observations); ``on_frame`` runs after reset and after every step."""
    obs = env.reset(configuration)
    if on_frame is not None:
        on_frame()
    observations = [obs]
    total, any_success, step = 0.0, False, None
    _t = 0
    for _t in range(env.max_episode_steps):  # noqa: B007 (_t is the episode length below)
        step = env.step(act(obs))
        obs = step.obs
        total += step.reward
        any_success |= step.success
        if keep_observations:
            observations.append(obs)
        if on_frame is not None:
            on_frame()
        if (stop_early and any_success) or step.terminated or step.truncated:
            break
    success = any_success if success_mode == "any_step" else bool(step is not None and step.success)
    return bool(success), total, _t + 1, observations


def random_policy(seed: int) -> ActFn:
    """Uniform random actions in [-1, 1]^4 from a seeded generator."""
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, size=ACT_DIM).astype(np.float32)
