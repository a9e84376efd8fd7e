"""Homeostatic excitability for feedforward actors (Section 3, Eq. 3; Table "Homeostatic excitability").

Each hidden neuron i carries a gain e_i in [e_min, e_max]; the activation is y_i = e_i * ReLU(w_i^T x). The gains
are buffers, not parameters: backpropagation and optimizers never see them. They change only through the local
rule of Eq. 3, driven by the neuron's own activity:

    a_bar_i <- (1 - beta) a_bar_i + beta * y_i,
    e_i     <- clip(e_i + eta_e * (alpha_target - a_bar_i), e_min, e_max),

with phase-specific rates eta_e (wake, sleep, and a faster "novelty" rate for the first episodes of the first
skill). y_i is the batch mean of the neuron's output in the forward pass that preceded the update. Both buffers
are part of the module's ``state_dict``, so they are saved with the model.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor, nn


@dataclass
class ExcitabilityConfig:
    """Paper Table "Homeostatic excitability hyperparameters for MT5"."""

    e_min: float = 0.1
    """Lower bound of the per-neuron gains e (paper 0.1)."""
    e_max: float = 5.0
    """Upper bound of the per-neuron gains e (paper 5.0)."""
    target: float = 0.10
    """alpha_target, the target activity of each neuron (paper 0.10)."""
    beta: float = 0.01
    """EMA factor of the activity estimate (paper 0.01)."""
    wake_rate: float = 1e-3
    """eta_e, the gain update rate during wake (paper 1e-3)."""
    sleep_rate: float = 1e-2
    """eta_e during sleep (paper 1e-2)."""
    novelty_rate: float = 5e-3
    """Gain update rate for the first novelty_episodes episodes of the first skill (paper 5e-3)."""
    novelty_episodes: int = 500
    """Length of that novelty period in episodes (paper 500; scaled by --wake.budget_scale)."""
    enabled: bool = True
    """Excitability at all - false is the "No exc." ablation (gains stay at 1, no updates)."""
    wake_enabled: bool = True
    """Gain updates during wake - false is the "Wake-exc off" ablation."""
    sleep_enabled: bool = True
    """Gain updates during sleep - false is the "Sleep-exc off" ablation."""

    def __post_init__(self) -> None:
        if not 0 < self.e_min <= 1.0 <= self.e_max:
            raise ValueError(f"need 0 < e_min <= 1 <= e_max, got [{self.e_min}, {self.e_max}]")
        if not 0 < self.beta <= 1:
            raise ValueError(f"beta must be in (0, 1], got {self.beta}")
        for name in ("wake_rate", "sleep_rate", "novelty_rate", "target"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.novelty_episodes < 0:
            raise ValueError(f"novelty_episodes must be >= 0, got {self.novelty_episodes}")

    def rate(self, phase: str, skill_index: int = 0, episode: int = 0) -> float:
        """eta_e for ``phase`` in {"wake", "sleep"}; the novelty rate applies to early episodes of skill 0."""
        if not self.enabled:
            return 0.0
        if phase == "wake":
            if not self.wake_enabled:
                return 0.0
            if skill_index == 0 and episode < self.novelty_episodes:
                return self.novelty_rate
            return self.wake_rate
        if phase == "sleep":
            return self.sleep_rate if self.sleep_enabled else 0.0
        raise ValueError(f"phase must be 'wake' or 'sleep', got {phase!r}")


class ExcitableReLU(nn.Module):
    """y = e * ReLU(x) with per-neuron gains e updated only by :meth:`homeostatic_update` (Eq. 3).

    Set ``record_activity = True`` (the default) to remember the batch-mean output of the last forward pass;
    :meth:`homeostatic_update` consumes it. The gain is applied as a constant in the graph (gradients flow to
    the layer's inputs, never to ``e``).
    """

    def __init__(self, num_features: int, config: ExcitabilityConfig | None = None) -> None:
        super().__init__()
        if num_features < 1:
            raise ValueError(f"num_features must be >= 1, got {num_features}")
        self.config = config or ExcitabilityConfig()
        self.num_features = num_features
        self.register_buffer("excitability", torch.ones(num_features))
        self.register_buffer("activity", torch.full((num_features,), self.config.target))
        self.record_activity = True
        self._last_activity: Tensor | None = None

    def forward(self, x: Tensor) -> Tensor:
        if x.shape[-1] != self.num_features:
            raise ValueError(f"expected last dimension {self.num_features}, got {tuple(x.shape)}")
        y = torch.relu(x) * self.excitability.detach()
        if self.record_activity:
            self._last_activity = y.detach().reshape(-1, self.num_features).mean(dim=0)
        return y

    @torch.no_grad()
    def homeostatic_update(self, rate: float) -> bool:
        """Apply Eq. 3 with rate ``rate`` using the last recorded activity; returns False if none was recorded."""
        if self._last_activity is None or rate == 0.0:
            return False
        beta = self.config.beta
        self.activity.mul_(1.0 - beta).add_(beta * self._last_activity.to(self.activity))
        self.excitability.add_(rate * (self.config.target - self.activity))
        self.excitability.clamp_(self.config.e_min, self.config.e_max)
        self._last_activity = None
        return True

    def extra_repr(self) -> str:
        c = self.config
        return f"{self.num_features}, bounds=[{c.e_min}, {c.e_max}], target={c.target}"


@contextmanager
def activity_recording_off(model: nn.Module) -> Iterator[None]:
    """Forward passes inside do not replace the recorded activity of ``model``'s excitable layers (a continual
    method's extra forward passes on memory states must not decide the wake's homeostatic update, Eq. 3)."""
    layers = [m for m in model.modules() if isinstance(m, ExcitableReLU)]
    before = [m.record_activity for m in layers]
    for m in layers:
        m.record_activity = False
    try:
        yield
    finally:
        for m, flag in zip(layers, before, strict=True):
            m.record_activity = flag


def update_excitability(model: nn.Module, rate: float) -> int:
    """Apply Eq. 3 to every :class:`ExcitableReLU` in ``model``; returns how many layers were updated."""
    return sum(int(m.homeostatic_update(rate)) for m in model.modules() if isinstance(m, ExcitableReLU))
