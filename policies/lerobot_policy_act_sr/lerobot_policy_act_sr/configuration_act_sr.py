"""ACT-SR configuration: LeRobot's ACT plus the Sleeping Robots wake objective.

Defaults follow the paper's SurgicAI table "ACT wake-training hyperparameters" (Appendix A.2: ResNet-18, chunk 16,
latent 32, KL weight 10, AdamW 1e-4 / backbone 1e-5, weight decay 1e-4, batch 8, distillation weights
gamma_2 = 1.0 and gamma_k = 0.5 for k >= 3). The policy holds what its own training step computes (ACT's loss plus
the wake-time distillation from attached memories). The stream's settings live in ``sr-train``'s sections, with
the same flag names on both substrates: ``--sleep.*`` (the table "Sleep-consolidation hyperparameters", core
:class:`~sr_imitation.core.sleep.SleepConfig`), ``--memory.buffer_size`` (1024 observations per skill).

``--policy.sleep`` (the design card's "a lerobot-style train command with ``--policy.sleep=true``") is the one sleep
setting the policy holds. On ``sr-train`` it is the same switch as ``--sleep.enabled`` and
``--policy.sleep_memory_size`` the same setting as ``--memory.buffer_size`` (folded into them at parse time,
:func:`sr_imitation.stream.config.fold_alias_flags`). On stock ``lerobot-train`` ``--policy.sleep=true`` makes
the policy keep a reservoir of the observations it trains on and write the skill's frozen actor memory
(``memory.safetensors``) next to every checkpoint, for a later sleep (:mod:`lerobot_policy_act_sr.modeling_act_sr`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig


def default_device() -> str:
    """The device of a config that names none: ``cuda``, else ``mps``, else ``cpu`` (LeRobot's own order), chosen
    quietly; a device that is named but absent still gets LeRobot's warning and the same fallback."""
    if torch.cuda.is_available():
        return "cuda"
    if torch.backends.mps.is_available():
        return "mps"
    return "cpu"


BACKBONE_NORMS = ("auto", "frozen_batch", "group")
"""Choices of :attr:`ACTSRConfig.backbone_norm`."""

DEFAULT_SLEEP_MEMORY_SIZE = 1024
"""Observations in the memory stock ``lerobot-train --policy.sleep=true`` writes when ``sleep_memory_size`` is not
given: the paper's |B_k| (SurgicAI table "Sleep-consolidation hyperparameters": 1024 buffered observations per
skill), the same as ``sr-train``'s ``--memory.buffer_size`` default."""


@PreTrainedConfig.register_subclass("act_sr")
@dataclass
class ACTSRConfig(ACTConfig):
    """ACT with frozen actor memories, wake-time distillation and Nash-bargained sleep.

    Every field has its meaning in the docstring under it (``--help`` of ``sr-train`` and of stock
    ``lerobot-train`` shows it); ACT's own fields are described by LeRobot's ``ACTConfig``. First lines of these
    docstrings avoid a single colon: draccus would read such a line as a field definition and show no help.
    """

    # ACT as in the paper (SurgicAI table "ACT wake-training hyperparameters").
    chunk_size: int = 16
    """Actions predicted per policy call, in environment steps (the paper's chunk 16; LeRobot's ACT 100)."""
    n_action_steps: int = 16
    """Actions of each chunk executed before the policy is called again (at most chunk_size)."""
    latent_dim: int = 32
    """Dimension of the VAE latent (paper 32)."""
    kl_weight: float = 10.0
    """Weight of the KL term when use_vae is true - loss = l1 + kl_weight * KL (paper 10)."""
    vision_backbone: str = "resnet18"
    """torchvision ResNet that encodes the camera images (paper ResNet-18; unused with use_images=false)."""
    pretrained_backbone_weights: str | None = None
    """torchvision weights of the backbone, e.g. ResNet18_Weights.IMAGENET1K_V1; null (default) - trained from
    scratch, so nothing is downloaded at run time."""
    optimizer_lr: float = 1e-4
    """AdamW learning rate of the wake (paper 1e-4)."""
    optimizer_lr_backbone: float = 1e-5
    """AdamW learning rate of the vision backbone during the wake (paper 1e-5)."""
    optimizer_weight_decay: float = 1e-4
    """AdamW weight decay of the wake (paper 1e-4)."""
    push_to_hub: bool = False
    """Push the trained policy to the Hugging Face Hub repository --policy.repo_id (sr-train - the consolidated
    policy at the end of the stream). Default false, unlike LeRobot - nothing leaves the machine unasked."""

    # Sleeping Robots' wake objective.
    distill_weight_second: float = 1.0
    """gamma_2, the wake distillation weight when learning the second skill (paper 1.0)."""
    distill_weight_later: float = 0.5
    """gamma_k, the wake distillation weight for the third skill and later (paper 0.5)."""
    distill_batch_size: int = 8
    """Observations drawn from each earlier skill's memory per wake step."""
    distill_reduction: str = "mean"
    """How a memory's squared chunk difference is reduced over the chunk's elements - mean (the "mean squared
    difference", on the per-element scale of ACT's l1 loss; default) or sum (the literal squared norm of the paper's
    equation, 112x larger for 16-step chunks of 7-d actions)."""
    use_images: bool = True
    """Feed the camera images to the model. false is ACT's state-only mode - the state is also fed as
    observation.environment_state and no camera is used (the CPU preset's choice)."""
    backbone_norm: str = "auto"
    """Normalization layers of the vision backbone - frozen_batch (LeRobot's ACT, FrozenBatchNorm2d with fixed
    statistics, right for ImageNet-pretrained weights), group (trainable GroupNorm with 16 channels per group; our
    choice, as Diffusion Policy does for a ResNet-18 trained from scratch) or auto (frozen_batch with
    pretrained_backbone_weights, group without). Why group without pretrained weights - a randomly initialized
    ResNet-18 with frozen batch norm has no normalization at all, so its features grow without bound during the
    wake and the image tokens drown the robot-state token (docs/RESULTS.md measures it on the CPU vision preset)."""

    # The design card's switch (``--policy.sleep=true``; None when not given).
    sleep: bool | None = None
    """Sleep switch (the design card's --policy.sleep=true). Stock lerobot-train - keep a reservoir of the trained-on
    observations and write the skill's frozen actor memory (memory.safetensors) beside each checkpoint's
    model.safetensors; false or null change nothing. sr-train - the same switch as --sleep.enabled (giving both with
    different values is an error); the other sleep and memory settings are the stream's (--sleep.*, --memory.*)."""
    sleep_memory_size: int | None = None
    """Observations in that memory (null - 1024, the paper's |B_k|); on sr-train the same as --memory.buffer_size."""

    def __post_init__(self) -> None:
        if self.device is None:  # LeRobot would pick the same device with a warning "Device 'None' is not available"
            self.device = default_device()
        super().__post_init__()
        bad = [] if self.distill_batch_size > 0 else [f"distill_batch_size={self.distill_batch_size}"]
        non_negative = {"distill_weight_second": self.distill_weight_second,
                        "distill_weight_later": self.distill_weight_later}
        bad += [f"{k}={v}" for k, v in non_negative.items() if not v >= 0]  # NaN fails too
        if bad:
            raise ValueError(f"invalid ACT-SR settings: {', '.join(bad)}")
        if self.distill_reduction not in ("mean", "sum"):
            raise ValueError(f"distill_reduction must be 'mean' or 'sum', got {self.distill_reduction!r}")
        if self.backbone_norm not in BACKBONE_NORMS:
            raise ValueError(f"backbone_norm must be one of {', '.join(BACKBONE_NORMS)}, got {self.backbone_norm!r}")
        if self.sleep_memory_size is not None and not self.sleep_memory_size >= 1:
            raise ValueError(f"policy.sleep_memory_size must be >= 1, got {self.sleep_memory_size}")

    @property
    def resolved_sleep_memory_size(self) -> int:
        """``sleep_memory_size`` with ``None`` resolved to :data:`DEFAULT_SLEEP_MEMORY_SIZE`."""
        return DEFAULT_SLEEP_MEMORY_SIZE if self.sleep_memory_size is None else self.sleep_memory_size

    @property
    def resolved_backbone_norm(self) -> str:
        """``backbone_norm`` with ``auto`` resolved: ``frozen_batch`` for pretrained weights, else ``group``."""
        if self.backbone_norm != "auto":
            return self.backbone_norm
        return "frozen_batch" if self.pretrained_backbone_weights else "group"

    def distill_weight(self, skill_number: int) -> float:
        """gamma_k of the wake objective for the k-th skill (1-based): 0, gamma_2, then gamma_later."""
        if skill_number < 1:
            raise ValueError(f"skill_number is 1-based, got {skill_number}")
        if skill_number == 1:
            return 0.0
        return self.distill_weight_second if skill_number == 2 else self.distill_weight_later
