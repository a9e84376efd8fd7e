"""Frozen critic memories for the SAC substrate (Section 3, "Wake phase and frozen skill memories"; Appendix A.1,
"Sleep consolidation", "Frozen critic validation and diagnostics", "Memory cost").

Memory M_i of skill i = the frozen twin critic Q_i, an unordered buffer B_i of 1000 raw states sampled uniformly
from the final 20% of wake episodes, and the snapshot nu_i of the observation normalizer at the end of wake. Its
skill objective for the current actor pi_theta is

    L_i(theta) = -E_{s ~ B_i} Q_i(nu_i(s), pi_theta(s)),

with Q_i = min(Q_i^1, Q_i^2) (clipped double-Q, the value SAC's actor maximizes) and pi_theta(s) the deterministic
action tanh(mean) of the actor on its own shared normalization. The critic's weights are memory tensors with
``requires_grad=False`` evaluated through ``torch.func.functional_call``: gradients reach the actor only.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sr_imitation.core.memory import Memory, register_memory
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.substrates.sac.config import CriticMemoryConfig, SACConfig
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent, TwinQ, normalize

logger = logging.getLogger(__name__)

CRITIC_PREFIX = "critic."


@register_memory
class CriticMemory(Memory):
    """Frozen twin critic + raw state buffer + normalizer snapshot; L_i = -E_s min Q_i(nu_i(s), pi_theta(s)).

    ``policy`` passed to :meth:`loss` is a callable mapping raw states (B x 39) to actions (B x 4) in [-1, 1],
    e.g. :meth:`SACAgent.policy_fn`.
    """

    kind = "sac_critic"
    contents = "states + the frozen twin critic + the observation normalizer's snapshot"
    buffer_keys = ("state",)

    def __init__(self, skill: str, tensors: Mapping[str, Tensor], config: Mapping[str, Any] | None = None):
        config = {"hidden_dim": 256, "layer_norm": True, "obs_dim": OBS_DIM, "act_dim": ACT_DIM,
                  "normalize": True, "clip": 10.0, "eps": 1e-8, **dict(config or {})}
        super().__init__(skill, tensors, config)
        skeleton = TwinQ(SACConfig(hidden_dim=int(config["hidden_dim"]), critic_layer_norm=bool(config["layer_norm"])),
                         int(config["obs_dim"]), int(config["act_dim"]))
        expected = {CRITIC_PREFIX + k: tuple(v.shape) for k, v in skeleton.state_dict().items()}
        got = {k: tuple(v.shape) for k, v in self.tensors.items() if k.startswith(CRITIC_PREFIX)}
        if expected != got:
            raise ValueError(f"critic tensors {sorted(got)} do not match the architecture {sorted(expected)}")
        skeleton.requires_grad_(False).eval()
        object.__setattr__(self, "_skeleton", skeleton)

    def _validate(self) -> None:
        super()._validate()
        for key in ("normalizer.mean", "normalizer.var"):
            if key not in self.tensors:
                raise ValueError(f"CriticMemory({self.skill!r}) is missing {key!r}")
        if self.tensors["state"].ndim != 2:
            raise ValueError(f"CriticMemory({self.skill!r}) state buffer must be N x obs_dim")

    @classmethod
    def from_agent(cls, skill: str, agent: SACAgent, states: np.ndarray | Tensor) -> CriticMemory:
        """Freeze ``agent``'s current critic and normalizer with the given raw ``states``."""
        tensors = {CRITIC_PREFIX + k: v.detach().cpu().float() for k, v in agent.critic.state_dict().items()}
        tensors["state"] = torch.as_tensor(np.asarray(states), dtype=torch.float32)
        tensors["normalizer.mean"] = agent.normalizer.mean.detach().cpu().clone()
        tensors["normalizer.var"] = agent.normalizer.var.detach().cpu().clone()
        enabled = bool(agent.normalizer.enabled and float(agent.normalizer.count) > 0)
        config = {"hidden_dim": agent.cfg.hidden_dim, "layer_norm": agent.cfg.critic_layer_norm,
                  "normalize": enabled, "clip": agent.normalizer.clip, "eps": agent.normalizer.eps}
        return cls(skill, tensors, config)

    def q_value(self, states: Tensor, actions: Tensor) -> Tensor:
        """min(Q_i^1, Q_i^2)(nu_i(s), a) with the frozen weights (differentiable in ``actions`` only)."""
        t = self._frozen_on(actions.device)
        x = states.to(actions.device, torch.float32)
        if self.config["normalize"]:
            x = normalize(x, t["normalizer.mean"], t["normalizer.var"], float(self.config["clip"]),
                          float(self.config["eps"])).float()
        params = {k.removeprefix(CRITIC_PREFIX): v for k, v in t.items() if k.startswith(CRITIC_PREFIX)}
        q1, q2 = torch.func.functional_call(self._skeleton, params, (x, actions))
        return torch.min(q1, q2)

    def _frozen_on(self, device: torch.device) -> dict[str, Tensor]:
        """The frozen critic and normalizer tensors on ``device``, copied there once (the memory is immutable), not
        at every sleep iteration."""
        cache: dict[torch.device, dict[str, Tensor]] = self.__dict__.setdefault("_on_device", {})
        if device not in cache:
            cache[device] = {k: v.to(device) for k, v in self.tensors.items()
                             if k.startswith(CRITIC_PREFIX) or k.startswith("normalizer.")}
        return cache[device]

    def loss(self, policy: Callable[[Tensor], Tensor], batch: Mapping[str, Tensor]) -> Tensor:
        states = batch["state"]
        actions = policy(states)
        if actions.shape != (states.shape[0], int(self.config["act_dim"])):
            raise ValueError(f"memory {self.skill!r}: policy returned actions of shape {tuple(actions.shape)}")
        return -self.q_value(states, actions).mean()

    ACTIONS_PER_STATE: int = 16
    """Uniform actions per state of :meth:`scale`."""

    @torch.no_grad()
    def scale(self, policy: Callable[[Tensor], Tensor], generator: torch.Generator) -> float:
        """The critic's action gap for ``policy``: | E_s [ Q_i(s, pi(s)) - E_{a ~ U[-1,1]^A} Q_i(s, a) ] | over the
        whole state buffer, 16 uniform actions per state drawn from ``generator``: the scale on which this critic
        tells the policy's action from a random one (``sleep.early_stop_scale=memory_scale``; our
        choice)."""
        states = self.tensors["state"]
        n, a = states.shape[0], int(self.config["act_dim"])
        random_actions = torch.rand(n * self.ACTIONS_PER_STATE, a, generator=generator) * 2 - 1
        repeated = states.repeat_interleave(self.ACTIONS_PER_STATE, dim=0)
        random_q = float(self.q_value(repeated, random_actions).mean())
        return abs(self.value(policy) - random_q)

    @torch.no_grad()
    def value(self, policy: Callable[[Tensor], Tensor], batch_size: int = 1000) -> float:
        """E_{s in B_i} Q_i(nu_i(s), pi(s)) over the whole buffer: the frozen-critic value diagnostic."""
        states = self.tensors["state"]
        total = 0.0
        for start in range(0, states.shape[0], batch_size):
            chunk = states[start : start + batch_size]
            total += float(self.q_value(chunk, policy(chunk)).sum())
        return total / states.shape[0]


def sample_late_states(replay: ReplayBuffer, episode_starts: Sequence[int], cfg: CriticMemoryConfig,
                       rng: np.random.Generator) -> np.ndarray:
    """``cfg.buffer_size`` raw states drawn uniformly from the final ``late_fraction`` of wake episodes.

    ``episode_starts`` are the global replay step numbers at which each wake episode began. Draws without
    replacement when there are enough late states, with replacement otherwise (tiny test budgets).
    """
    if not episode_starts:
        raise ValueError("no wake episodes to sample memory states from")
    n_late = max(1, math.ceil(cfg.late_fraction * len(episode_starts)))
    first = int(episode_starts[-n_late])
    available = replay.total - first
    if available <= 0:
        raise ValueError("the late wake episodes contain no transitions")
    if available >= cfg.buffer_size:
        offsets = rng.choice(available, size=cfg.buffer_size, replace=False)
    else:
        offsets = rng.integers(0, available, size=cfg.buffer_size)
    return replay.states_at(first + np.sort(offsets))


def validate_critic(agent: SACAgent, holdout: ReplayBuffer, replay: ReplayBuffer, cfg: CriticMemoryConfig,
                    rng: np.random.Generator) -> dict[str, Any]:
    """Check the critic's normalized Bellman residual on held-out wake transitions before freezing it; if it
    exceeds ``cfg.validation_threshold``, run ``cfg.validation_chunk`` critic-only updates on the wake replay
    and re-check, at most ``cfg.validation_max_rounds`` times (Appendix A.1, "Frozen critic validation").
    """
    source = holdout if len(holdout) > 0 else replay
    idx = source.indices(min(cfg.holdout_batch, max(1, len(source))), rng)
    batch = source.batch(idx, agent.device)
    residuals = [agent.bellman_residual(batch)]
    extra = 0
    batch_size = agent.cfg.batch_size
    for _ in range(cfg.validation_max_rounds):
        if residuals[-1] <= cfg.validation_threshold or cfg.validation_chunk == 0 or len(replay) < 1:
            break
        for _ in range(cfg.validation_chunk):
            agent.critic_only_update(replay.batch(replay.indices(batch_size, rng), agent.device))
        extra += cfg.validation_chunk
        residuals.append(agent.bellman_residual(batch))
    passed = residuals[-1] <= cfg.validation_threshold
    log = logger.info if passed else logger.warning
    log("critic validation: normalized Bellman residual %s (threshold %g), %d extra updates, %s",
        [round(r, 4) for r in residuals], cfg.validation_threshold, extra, "passed" if passed else "NOT passed")
    return {"residuals": residuals, "extra_updates": extra, "passed": passed,
            "holdout_transitions": len(holdout), "threshold": cfg.validation_threshold}
