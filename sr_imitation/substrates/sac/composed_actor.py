"""CompoNet's actor for the SAC substrate (:mod:`sr_imitation.substrates.sac.methods.componet` explains the method): a
trunk frozen after the first skill, a Gaussian head and an attention over the heads per skill."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.substrates.sac.config import SACConfig
from sr_imitation.substrates.sac.sac import Actor, RunningNormalizer

SELF_BIAS = 2.0
"""Initial attention logit of a module on its own head (paper: self-bias 2.0)."""


class ComposedActor(Actor):
    """Frozen-after-skill-1 trunk, one Gaussian head and one attention per skill (see the module docstring).
    ``select_skill(j)`` chooses the module that acts; ``train_skill(j)`` sets what learns in wake j."""

    def __init__(self, cfg: SACConfig, n_skills: int, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> None:
        nn.Module.__init__(self)
        h = cfg.hidden_dim
        self.fc1, self.fc2 = nn.Linear(obs_dim, h), nn.Linear(h, h)
        self.act1, self.act2 = nn.ReLU(), nn.ReLU()
        self.heads_mean = nn.ModuleList(nn.Linear(h, act_dim) for _ in range(n_skills))
        self.heads_log_std = nn.ModuleList(nn.Linear(h, act_dim) for _ in range(n_skills))
        for head in self.heads_log_std:
            nn.init.constant_(head.bias, cfg.actor_log_std_bias_init)
        self.attention = nn.ModuleList(nn.Linear(h, j + 1) for j in range(n_skills))
        with torch.no_grad():
            for j, att in enumerate(self.attention):
                att.weight.zero_()
                att.bias.zero_()
                att.bias[j] = SELF_BIAS
        self.log_std_min, self.log_std_max = cfg.log_std_min, cfg.log_std_max
        self.active = 0
        # the observation normalizer's statistics at the end of each module's wake (count 0: not taken yet); the
        # agent's normalizer keeps updating in later wakes, so a frozen module acts exactly as it did only on its own
        # statistics (our choice; saved with the actor, so a resumed run has them)
        self.register_buffer("norm_mean", torch.zeros(n_skills, obs_dim, dtype=torch.float64))
        self.register_buffer("norm_var", torch.ones(n_skills, obs_dim, dtype=torch.float64))
        self.register_buffer("norm_count", torch.zeros(n_skills, dtype=torch.float64))

    def select_skill(self, j: int) -> None:
        if not 0 <= j < len(self.heads_mean):
            raise ValueError(f"skill index {j} outside 0..{len(self.heads_mean) - 1}")
        self.active = j

    def train_skill(self, j: int) -> None:
        """Act with module j and let only what wake j trains have gradients."""
        self.select_skill(j)
        self.requires_grad_(False)
        for module in (self.heads_mean[j], self.heads_log_std[j], self.attention[j]):
            module.requires_grad_(True)
        if j == 0:
            for module in (self.fc1, self.fc2):
                module.requires_grad_(True)

    @torch.no_grad()
    def snapshot_normalizer(self, j: int, normalizer: RunningNormalizer) -> None:
        """Keep ``normalizer``'s statistics as module j's (called at the end of wake j)."""
        self.norm_mean[j].copy_(normalizer.mean)
        self.norm_var[j].copy_(normalizer.var)
        self.norm_count[j].copy_(normalizer.count)

    def module_normalizer(self, j: int, normalizer: RunningNormalizer) -> RunningNormalizer:
        """The normalizer module j acts with: its end-of-wake statistics, or ``normalizer`` before they exist."""
        if self.norm_count[j] == 0:
            return normalizer
        frozen = RunningNormalizer(self.norm_mean.shape[1], enabled=normalizer.enabled, clip=normalizer.clip,
                                   eps=normalizer.eps).to(normalizer.mean.device)
        frozen.mean.copy_(self.norm_mean[j])
        frozen.var.copy_(self.norm_var[j])
        frozen.count.copy_(self.norm_count[j])
        frozen.refresh_seen()
        return frozen

    def attention_weights(self, obs: Tensor) -> Tensor:
        """softmax over modules 1..j of the active module j (B x j)."""
        return torch.softmax(self.attention[self.active](self._features(obs)), dim=-1)

    def _features(self, obs: Tensor) -> Tensor:
        return self.act2(self.fc2(self.act1(self.fc1(obs))))

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        x = self._features(obs)
        j = self.active
        means = torch.stack([self.heads_mean[i](x) for i in range(j + 1)], dim=1)
        log_stds = torch.stack([self.heads_log_std[i](x).clamp(self.log_std_min, self.log_std_max)
                                for i in range(j + 1)], dim=1)
        w = torch.softmax(self.attention[j](x), dim=-1).unsqueeze(-1)
        return (w * means).sum(1), (w * log_stds).sum(1)
