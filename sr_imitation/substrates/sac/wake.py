"""Wake phase: SAC on one skill with the paper's episode budgets and early stopping (Appendix A.1, "Wake budgets
and early stopping"; Algorithm 1, line 3), then the skill's frozen critic memory (line 4).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from sr_imitation.core.excitability import ExcitabilityConfig, activity_recording_off
from sr_imitation.envs.metaworld.tasks import SkillEnv
from sr_imitation.progress import Progress
from sr_imitation.stream.methods.base import ContinualMethod, WakeHooks
from sr_imitation.substrates.sac import wake_snapshot
from sr_imitation.substrates.sac.config import CriticMemoryConfig, SACConfig, SkillBudget, WakeConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory, sample_late_states, validate_critic
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent

logger = logging.getLogger(__name__)


def rolling_means(rewards: list[float], window: int) -> np.ndarray:
    """Mean of the last ``window`` episode rewards after each episode (fewer at the start)."""
    r = np.asarray(rewards, dtype=np.float64)
    c = np.concatenate([[0.0], np.cumsum(r)])
    idx = np.arange(1, len(r) + 1)
    lo = np.maximum(0, idx - window)
    return (c[idx] - c[lo]) / (idx - lo)


def should_stop_early(rewards: list[float], budget: SkillBudget, window: int, improvement: float) -> bool:
    """Early-stopping rule: after ``min_episodes``, stop when the best rolling mean reward of the last
    ``patience`` episodes is not more than ``improvement`` (2%) above the best rolling mean before them."""
    n = len(rewards)
    if n < budget.min_episodes or n <= budget.patience:
        return False
    rolling = rolling_means(rewards, window)
    before = float(rolling[: n - budget.patience].max())
    recent = float(rolling[n - budget.patience :].max())
    return recent <= before + improvement * abs(before)


@dataclass
class WakeResult:
    skill: str
    episodes: int
    env_steps: int
    updates: int
    stop_reason: str
    episode_rewards: list[float] = field(default_factory=list)
    episode_successes: list[bool] = field(default_factory=list)
    critic_validation: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    #: wall time the wake had run before the snapshot it was resumed from (0 for a wake run in one process); part of
    #: ``seconds``, and what a caller timing the whole phase adds to its own clock (not in :meth:`summary`)
    seconds_before_resume: float = 0.0
    last_update: dict[str, float] = field(default_factory=dict)
    method: dict[str, float] = field(default_factory=dict)
    state_sample: Tensor | None = None
    transition_sample: dict[str, Tensor] | None = None

    def summary(self) -> dict[str, Any]:
        k = max(1, len(self.episode_rewards) // 10)
        return {
            "skill": self.skill, "episodes": self.episodes, "env_steps": self.env_steps, "updates": self.updates,
            "stop_reason": self.stop_reason, "seconds": round(self.seconds, 2),
            "final_train_reward": float(np.mean(self.episode_rewards[-k:])) if self.episode_rewards else None,
            "final_train_success": float(np.mean(self.episode_successes[-k:])) if self.episode_successes else None,
            "critic_validation": self.critic_validation, "last_update": self.last_update,
            **({"method": self.method} if self.method else {}),
        }


def train_skill(
    agent: SACAgent,
    env: SkillEnv,
    skill_index: int,
    sac_cfg: SACConfig,
    wake_cfg: WakeConfig,
    exc_cfg: ExcitabilityConfig,
    memory_cfg: CriticMemoryConfig,
    seed: int,
    progress: bool = True,
    method: ContinualMethod | None = None,
    snapshot: Path | None = None,
) -> tuple[WakeResult, CriticMemory]:
    """Train ``agent`` on one skill and freeze its critic memory.

    Fresh replay buffer and optimizer states per skill (no earlier transitions are available); ``warmup_steps``
    uniform random actions first; then ``utd_ratio`` SAC updates per environment step, each followed by the
    actor's homeostatic update at the wake rate (the novelty rate during the first, scaled, 500 episodes of the
    first skill). Stops at the scaled ``max_episodes`` or by :func:`should_stop_early`. A ``method`` with wake
    hooks shapes every actor update (:class:`~sr_imitation.stream.methods.base.WakeHooks`); its averaged numbers
    are ``result.method``.

    ``snapshot``: where the wake keeps its snapshot (:mod:`sr_imitation.substrates.sac.wake_snapshot`), written at an
    episode boundary every ``wake_cfg.snapshot_every_s`` seconds (never if negative); a wake
    that finds one continues from it with identical results, and removes it when it ends. Not used with wake hooks
    that do not declare their state (``not hooks.resumable``).
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    env.seed(seed)
    budget = wake_cfg.budget_for(env.skill)
    window = wake_cfg.scaled_window
    exc_cfg = dataclasses.replace(exc_cfg, novelty_episodes=wake_cfg.scaled(exc_cfg.novelty_episodes)
                                  if exc_cfg.novelty_episodes > 0 else 0)
    replay = ReplayBuffer(sac_cfg.buffer_size)
    holdout = ReplayBuffer(max(1, int(memory_cfg.holdout_batch)))
    agent.reset_optimizers(reset_alpha=True)
    result = WakeResult(env.skill, 0, 0, 0, "max_episodes")
    episode_starts: list[int] = []
    update_credit = 0.0
    info = None
    hooks = None
    if method is not None and method.has_wake_hooks:  # the actor's recorded activity is left alone by the hooks
        hooks = WakeHooks(method, skill_index, agent.actor_parameters(), agent.policy_fn, seed,
                          quiet=lambda: activity_recording_off(agent.actor))
        if not hooks.resumable:
            snapshot = None  # hooks that do not declare their state: such a wake, killed, starts again
    every_s = wake_cfg.snapshot_every_s  # negative: none written (one found is still continued from, then removed)
    identity = {"skill": env.skill, "skill_index": skill_index, "seed": seed % (2**63)}
    if snapshot is not None and snapshot.is_file():
        loop = wake_snapshot.load(snapshot, identity, agent, env, replay, holdout, rng, hooks)
        result.episodes, result.env_steps, result.updates = loop.episodes, loop.env_steps, loop.updates
        result.episode_rewards, result.episode_successes = loop.episode_rewards, loop.episode_successes
        episode_starts, update_credit, info = loop.episode_starts, loop.update_credit, loop.info
        t0 -= loop.seconds
        result.seconds_before_resume = loop.seconds
        logger.info("wake %s: resumed from %s after %d episodes (%d steps, %d updates)", env.skill, snapshot,
                    result.episodes, result.env_steps, result.updates)
    last_snapshot = time.perf_counter()
    bar = Progress(budget.max_episodes, f"wake {env.skill}", logger, enabled=progress, unit="ep",
                   initial=result.episodes)
    for episode in range(result.episodes, budget.max_episodes):
        bar.update(1)
        episode_starts.append(replay.total)
        rate = exc_cfg.rate("wake", skill_index, episode)
        total, success, update_credit, info = _episode(agent, env, rng, replay, holdout, result, sac_cfg, memory_cfg,
                                                       rate, hooks, update_credit, info)
        result.episodes += 1
        result.episode_rewards.append(total)
        result.episode_successes.append(bool(success))
        if progress and episode % 5 == 0:
            bar.set_postfix(reward=f"{total:.1f}", success=int(success), alpha=f"{agent.alpha:.3g}")
        if wake_cfg.early_stopping and should_stop_early(result.episode_rewards, budget, window,
                                                         wake_cfg.improvement):
            result.stop_reason = "early_stopping"
            break
        if snapshot is not None and every_s >= 0 and time.perf_counter() - last_snapshot >= every_s:
            loop = wake_snapshot.WakeLoop(result.episode_rewards, result.episode_successes, episode_starts,
                                          result.env_steps, result.updates, update_credit, info,
                                          time.perf_counter() - t0)
            wake_snapshot.save(snapshot, identity, loop, agent, env, replay, holdout, rng, hooks)
            last_snapshot = time.perf_counter()
    bar.close()
    if result.updates:
        result.last_update = dataclasses.asdict(info)
    logger.info("wake %s: %d episodes, %d steps, %d updates, stop: %s", env.skill, result.episodes,
                result.env_steps, result.updates, result.stop_reason)

    if hooks is not None:
        result.method = hooks.summary()
    result.critic_validation = validate_critic(agent, holdout, replay, memory_cfg, rng)
    # episode starts were recorded as replay positions (held-out transitions never enter the replay)
    starts = [min(s, replay.total - 1) for s in episode_starts]
    states = sample_late_states(replay, starts, memory_cfg, rng)
    memory = CriticMemory.from_agent(env.skill.removesuffix("-v3"), agent, states)
    _method_samples(result, replay, method, seed)
    result.seconds = time.perf_counter() - t0
    if snapshot is not None:
        snapshot.unlink(missing_ok=True)
    return result, memory


def _episode(agent: SACAgent, env: SkillEnv, rng: np.random.Generator, replay: ReplayBuffer, holdout: ReplayBuffer,
             result: WakeResult, sac_cfg: SACConfig, memory_cfg: CriticMemoryConfig, rate: float,
             hooks: WakeHooks | None, update_credit: float, info: Any) -> tuple[float, bool, float, Any]:
    """One wake episode: uniform random actions until ``warmup_steps`` environment steps, the actor's after; each
    transition to the replay (or, with probability ``holdout_fraction``, to the critic's held-out set); after the
    warm-up, ``utd_ratio`` SAC updates per environment step (fractional credit carried over), each with the
    homeostatic ``rate``. Returns (episode reward, any-step success, the carried update credit, the last update's
    info)."""
    obs = env.reset()
    total, success = 0.0, False
    while True:
        if result.env_steps < sac_cfg.warmup_steps:
            action = rng.uniform(-1.0, 1.0, size=4).astype(np.float32)
        else:
            action = agent.act(obs)
        step = env.step(action)
        agent.normalizer.update(obs)
        if rng.random() < memory_cfg.holdout_fraction:
            holdout.add(obs, action, step.reward, step.obs, step.terminated)
        else:
            replay.add(obs, action, step.reward, step.obs, step.terminated)
        result.env_steps += 1
        total += step.reward
        success |= step.success
        obs = step.obs
        if result.env_steps >= sac_cfg.warmup_steps and len(replay) >= sac_cfg.batch_size:
            update_credit += sac_cfg.utd_ratio
            while update_credit >= 1.0:
                info = agent.update(replay.batch(replay.indices(sac_cfg.batch_size, rng), agent.device), rate, hooks)
                result.updates += 1
                update_credit -= 1.0
        if step.terminated or step.truncated:
            return total, success, update_credit, info


def _method_samples(result: WakeResult, replay: ReplayBuffer, method: ContinualMethod | None, seed: int) -> None:
    """What a method needs from the replay at skill end, uniform over it, from its own generators (the rest of the
    run is unchanged): states (EWC's Fisher) or whole transitions (CLEAR)."""
    n_states = method.wake_state_sample if method is not None else 0
    if n_states > 0:
        own = np.random.default_rng([seed % (2**63), 7])
        result.state_sample = replay.batch(own.integers(0, len(replay), size=n_states))["obs"]
    n_transitions = method.wake_transition_sample if method is not None else 0
    if n_transitions > 0:
        own = np.random.default_rng([seed % (2**63), 8])
        result.transition_sample = replay.batch(own.integers(0, len(replay), size=n_transitions))

