"""Soft Actor-Critic for the wake phase, CleanRL style: everything one SAC update does, top to bottom.

Architecture and settings follow Appendix A.1 ("Policy and critic architecture", Table "SAC hyperparameters"):

* actor: 39 -> 256 -> 256 MLP with ReLU, each hidden unit carrying a homeostatic excitability gain
  (:class:`~sr_imitation.core.excitability.ExcitableReLU`, Eq. 3), diagonal Gaussian head squashed by tanh, the
  log-std bias initialised to -1;
* twin Q-networks: (39 + 4) -> 256 -> 256 -> 1 with LayerNorm and ReLU, Polyak-averaged targets (tau 0.005);
* automatic entropy tuning: target entropy -2, Adam 3e-4 on log alpha, clamped to [-10, 4];
* replay with time-limit truncations stored as non-terminal (``done`` is the environment's ``terminated``);
* a running mean/std observation normalizer nu shared by actor and critic during wake; each critic memory keeps
  a snapshot of it.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sr_imitation.core.excitability import ExcitabilityConfig, ExcitableReLU, update_excitability
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.substrates.sac.config import SACConfig


# ---------------------------------------------------------------------------------------------------------
# Observation normalizer nu
# ---------------------------------------------------------------------------------------------------------
class RunningNormalizer(nn.Module):
    """Running mean/variance of observations (parallel Welford); ``forward`` returns clipped z-scores.

    State lives in buffers (``mean``, ``var``, ``count``) so it is saved with the agent and snapshotted into
    critic memories. ``enabled=False`` makes it the identity.
    """

    def __init__(self, dim: int, enabled: bool = True, clip: float = 10.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.enabled, self.clip, self.eps = enabled, clip, eps
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("var", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        # whether count > 0, kept on the host so that forward never reads the device (a sync per call on a GPU)
        self._seen = False
        self.register_load_state_dict_post_hook(lambda module, _keys: module.refresh_seen())

    def refresh_seen(self) -> None:
        self._seen = bool(self.count != 0)

    @torch.no_grad()
    def update(self, x: np.ndarray) -> None:
        if not self.enabled:
            return
        x = torch.as_tensor(np.atleast_2d(x), dtype=torch.float64, device=self.mean.device)
        n, mean, var = x.shape[0], x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.mean += delta * n / total
        self.var.copy_((self.var * self.count + var * n + delta.pow(2) * self.count * n / total) / total)
        self.count.copy_(total)
        self._seen = self._seen or n > 0

    def forward(self, x: Tensor) -> Tensor:
        if not self.enabled or not self._seen:
            return x
        return normalize(x, self.mean, self.var, self.clip, self.eps)


def normalize(x: Tensor, mean: Tensor, var: Tensor, clip: float = 10.0, eps: float = 1e-8) -> Tensor:
    """(x - mean) / sqrt(var + eps), clipped to [-clip, clip]."""
    z = (x - mean.to(x.dtype)) / torch.sqrt(var.to(x.dtype) + eps)
    return z.clamp(-clip, clip)


# ---------------------------------------------------------------------------------------------------------
# Networks
# ---------------------------------------------------------------------------------------------------------
class Actor(nn.Module):
    """Gaussian tanh policy on normalized observations; hidden ReLUs carry excitability gains (Eq. 3).

    With ``excitability=None`` the hidden activations are plain ReLUs (the "plain SAC" reference of the
    benchmark); the "No exc." ablation instead keeps :class:`ExcitableReLU` with updates disabled (gains stay 1).
    """

    def __init__(self, cfg: SACConfig, excitability: ExcitabilityConfig | None, obs_dim: int = OBS_DIM,
                 act_dim: int = ACT_DIM) -> None:
        super().__init__()
        h = cfg.hidden_dim
        self.fc1, self.fc2 = nn.Linear(obs_dim, h), nn.Linear(h, h)
        make_act = (lambda: ExcitableReLU(h, excitability)) if excitability is not None else nn.ReLU
        self.act1, self.act2 = make_act(), make_act()
        self.fc_mean, self.fc_log_std = nn.Linear(h, act_dim), nn.Linear(h, act_dim)
        nn.init.constant_(self.fc_log_std.bias, cfg.actor_log_std_bias_init)
        self.log_std_min, self.log_std_max = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        x = self.act2(self.fc2(self.act1(self.fc1(obs))))
        log_std = self.fc_log_std(x).clamp(self.log_std_min, self.log_std_max)
        return self.fc_mean(x), log_std

    def sample(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Reparameterized tanh-Gaussian action, its log-probability, and the deterministic action tanh(mean)."""
        mean, log_std = self(obs)
        # no argument validation: it reads every value back to the host (a sync per call on a GPU); the actor's
        # outputs are finite by construction (tanh-bounded log std), non-finite losses are caught by the trainer
        normal = torch.distributions.Normal(mean, log_std.exp(), validate_args=False)
        u = normal.rsample()
        action = torch.tanh(u)
        log_prob = normal.log_prob(u) - torch.log(1.0 - action.pow(2) + 1e-6)
        return action, log_prob.sum(-1, keepdim=True), torch.tanh(mean)

    def mean_action(self, obs: Tensor) -> Tensor:
        """Deterministic action tanh(mean): used for evaluation and by the critic-memory objective."""
        return torch.tanh(self(obs)[0])


class QNetwork(nn.Module):
    """Q(s, a): (obs + act) -> 256 -> 256 -> 1 with LayerNorm before each ReLU."""

    def __init__(self, cfg: SACConfig, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> None:
        super().__init__()
        h = cfg.hidden_dim
        norm = (lambda: nn.LayerNorm(h)) if cfg.critic_layer_norm else nn.Identity
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, h), norm(), nn.ReLU(),
            nn.Linear(h, h), norm(), nn.ReLU(),
            nn.Linear(h, 1),
        )

    def forward(self, obs: Tensor, action: Tensor) -> Tensor:
        return self.net(torch.cat([obs, action], dim=-1))


class TwinQ(nn.Module):
    """The twin critic (Q1, Q2); ``min_q`` is the clipped double-Q value used by targets and memories."""

    def __init__(self, cfg: SACConfig, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> None:
        super().__init__()
        self.q1, self.q2 = QNetwork(cfg, obs_dim, act_dim), QNetwork(cfg, obs_dim, act_dim)

    def forward(self, obs: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        return self.q1(obs, action), self.q2(obs, action)

    def min_q(self, obs: Tensor, action: Tensor) -> Tensor:
        q1, q2 = self(obs, action)
        return torch.min(q1, q2)


# ---------------------------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------------------------
class ReplayBuffer:
    """FIFO transitions (s, a, r, s', terminated) in preallocated numpy arrays; raw (unnormalized) states.

    ``total`` counts every transition ever added, so global step g lives at index ``g % capacity`` while
    ``total - g <= capacity``.
    """

    def __init__(self, capacity: int, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> None:
        if capacity < 1:
            raise ValueError(f"replay capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.actions = np.zeros((capacity, act_dim), np.float32)
        self.rewards = np.zeros((capacity, 1), np.float32)
        self.terminated = np.zeros((capacity, 1), np.float32)
        self.total = 0

    def __len__(self) -> int:
        return min(self.total, self.capacity)

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray,
            terminated: bool) -> None:
        i = self.total % self.capacity
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)
        self.total += 1

    def indices(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        return rng.integers(0, len(self), size=batch_size)

    def batch(self, idx: np.ndarray, device: torch.device | str = "cpu") -> dict[str, Tensor]:
        def t(a: np.ndarray) -> Tensor:
            return torch.as_tensor(a[idx], device=device)

        return {"obs": t(self.obs), "actions": t(self.actions), "rewards": t(self.rewards),
                "next_obs": t(self.next_obs), "terminated": t(self.terminated)}

    def states_at(self, global_steps: np.ndarray) -> np.ndarray:
        """Raw states of the given global step numbers (must still be in the buffer)."""
        global_steps = np.asarray(global_steps)
        if global_steps.size and (global_steps.min() < self.total - self.capacity or global_steps.max() >= self.total):
            raise ValueError("requested replay steps are no longer (or not yet) in the buffer")
        return self.obs[global_steps % self.capacity].copy()


# ---------------------------------------------------------------------------------------------------------
# Agent
# ---------------------------------------------------------------------------------------------------------
@dataclass
class UpdateInfo:
    critic_loss: float
    actor_loss: float
    alpha: float
    alpha_loss: float
    q_mean: float
    entropy: float


class ActorHooks(Protocol):
    """A continual method's say in the update (see :meth:`SACAgent.update`)."""

    def batch(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The batch critic and actor train on instead of ``batch`` (the current skill's replay sample)."""

    def loss(self, actor_loss: Tensor) -> Tensor:
        """The objective to differentiate instead of ``actor_loss`` (SAC's own actor loss on the batch)."""

    def adjust(self) -> None:
        """Change the actor's ``.grad`` after the backward pass."""


class SACAgent(nn.Module):
    """Actor, twin critic with target, log alpha, observation normalizer, and their optimizers."""

    def __init__(self, cfg: SACConfig, excitability: ExcitabilityConfig | None = None,
                 device: str | torch.device = "cpu", plain_actor: bool = False) -> None:
        super().__init__()
        self.cfg = cfg
        self.normalizer = RunningNormalizer(OBS_DIM, enabled=cfg.normalize_observations)
        self.actor = Actor(cfg, None if plain_actor else (excitability or ExcitabilityConfig()))
        self.critic = TwinQ(cfg)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(float(cfg.initial_log_alpha)))
        self.to(device)
        self.device = torch.device(device)
        self.reset_optimizers()

    def reset_optimizers(self, reset_alpha: bool = False) -> None:
        """Fresh Adam states (done at the start of every skill); optionally reset alpha to its initial value."""
        if reset_alpha:
            with torch.no_grad():
                self.log_alpha.fill_(self.cfg.initial_log_alpha)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=self.cfg.actor_lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.critic_lr)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=self.cfg.alpha_lr)

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """One action for one raw observation."""
        x = self.normalizer(torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0))
        if deterministic:
            return self.actor.mean_action(x)[0].cpu().numpy()
        return self.actor.sample(x)[0][0].cpu().numpy()

    def policy_fn(self, states: Tensor) -> Tensor:
        """pi_theta(s) on raw states with the actor's shared normalizer (what critic memories evaluate)."""
        return self.actor.mean_action(self.normalizer(states.to(self.device, torch.float32)).float())

    def update(self, batch: dict[str, Tensor], excitability_rate: float = 0.0,
               actor_hooks: ActorHooks | None = None) -> UpdateInfo:
        """One SAC gradient step on critic, actor and alpha, then the actor's homeostatic update (Eq. 3).

        ``actor_hooks`` (a continual method's wake hooks, :class:`sr_imitation.stream.methods.base.WakeHooks`) may
        replace the batch (critic and actor) and the actor loss before its backward pass, and change the actor's
        gradients before its optimizer step; their forward passes do not count as the actor's recorded activity."""
        cfg = self.cfg
        if actor_hooks is not None:
            batch = actor_hooks.batch(batch)
        obs = self.normalizer(batch["obs"]).float()
        next_obs = self.normalizer(batch["next_obs"]).float()
        actions, rewards = batch["actions"], batch["rewards"] * cfg.reward_scale
        alpha = self.log_alpha.detach().exp()

        # 1) critic: soft Bellman target with clipped double Q; time-limit truncations are not terminal
        with torch.no_grad():
            next_actions, next_log_prob, _ = self.actor.sample(next_obs)
            next_q = self.critic_target.min_q(next_obs, next_actions) - alpha * next_log_prob
            target_q = rewards + (1.0 - batch["terminated"]) * cfg.gamma * next_q
        q1, q2 = self.critic(obs, actions)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()

        # 2) actor: maximize E[min Q(s, a~pi) - alpha log pi(a|s)]
        new_actions, log_prob, _ = self.actor.sample(obs)
        q_pi = self.critic.min_q(obs, new_actions)
        actor_loss = (alpha * log_prob - q_pi).mean()
        objective = actor_loss if actor_hooks is None else actor_hooks.loss(actor_loss)
        self.actor_optimizer.zero_grad(set_to_none=True)
        objective.backward()
        if actor_hooks is not None:
            actor_hooks.adjust()
        self.actor_optimizer.step()
        self.critic_optimizer.zero_grad(set_to_none=True)  # the actor loss left gradients on the critic

        # 3) temperature: drive the policy entropy toward the target (-2), log alpha clamped to [-10, 4]
        alpha_loss = (-self.log_alpha * (log_prob.detach() + cfg.target_entropy)).mean()
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optimizer.step()
        with torch.no_grad():
            self.log_alpha.clamp_(cfg.log_alpha_min, cfg.log_alpha_max)

        # 4) Polyak-averaged target critic
        with torch.no_grad():
            for p, tp in zip(self.critic.parameters(), self.critic_target.parameters(), strict=True):
                tp.lerp_(p, cfg.tau)

        # 5) homeostatic excitability from the actor-loss forward pass (last recorded activity), Eq. 3
        if excitability_rate > 0.0:
            update_excitability(self.actor, excitability_rate)

        return UpdateInfo(float(critic_loss.detach()), float(actor_loss.detach()), float(alpha),
                          float(alpha_loss.detach()),
                          float(q1.detach().mean()), float(-log_prob.detach().mean()))

    def critic_only_update(self, batch: dict[str, Tensor]) -> float:
        """A critic + target step with the actor fixed (extra updates when critic validation fails)."""
        obs = self.normalizer(batch["obs"]).float()
        next_obs = self.normalizer(batch["next_obs"]).float()
        with torch.no_grad():
            next_actions, next_log_prob, _ = self.actor.sample(next_obs)
            next_q = self.critic_target.min_q(next_obs, next_actions) - self.log_alpha.exp() * next_log_prob
            target_q = batch["rewards"] * self.cfg.reward_scale + (1 - batch["terminated"]) * self.cfg.gamma * next_q
        q1, q2 = self.critic(obs, batch["actions"])
        loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        with torch.no_grad():
            for p, tp in zip(self.critic.parameters(), self.critic_target.parameters(), strict=True):
                tp.lerp_(p, self.cfg.tau)
        return float(loss.detach())

    @torch.no_grad()
    def bellman_residual(self, batch: dict[str, Tensor]) -> float:
        """Normalized Bellman residual RMSE(Q - target) / std(target) on ``batch`` (critic validation)."""
        obs = self.normalizer(batch["obs"]).float()
        next_obs = self.normalizer(batch["next_obs"]).float()
        next_actions, next_log_prob, _ = self.actor.sample(next_obs)
        next_q = self.critic_target.min_q(next_obs, next_actions) - self.log_alpha.exp() * next_log_prob
        target = batch["rewards"] * self.cfg.reward_scale + (1 - batch["terminated"]) * self.cfg.gamma * next_q
        q1, q2 = self.critic(obs, batch["actions"])
        rmse = math.sqrt(0.5 * float((q1 - target).pow(2).mean() + (q2 - target).pow(2).mean()))
        spread = float(target.std()) if target.numel() > 1 else 0.0  # one sample has no spread (std would be NaN)
        return rmse / max(spread, 1e-6)

    def actor_parameters(self) -> list[nn.Parameter]:
        """theta: the shared policy's trainable parameters (excitability gains are buffers, not included)."""
        return [p for p in self.actor.parameters() if p.requires_grad]
