"""ACT-SR configuration: LeRobot's ACT plus the Sleeping Robots wake/sleep settings.

Defaults follow the paper's SurgicAI tables (Appendix A.2): "ACT wake-training hyperparameters" (ResNet-18,
chunk 16, latent 32, KL weight 10, AdamW 1e-4 / backbone 1e-5, weight decay 1e-4, batch 8, distillation weights
gamma_2 = 1.0 and gamma_k = 0.5 for k >= 3) and "Sleep-consolidation hyperparameters" (Adam 1e-5, at most 1000
iterations, batch 8, tolerance 1e-3 on the windowed objective, 5 Frank-Wolfe iterations, per-skill l2
normalization, 1024 buffered observations per skill, anchor 1e-2).
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig

from sr_imitation.core.aggregation import AGGREGATORS
from sr_imitation.core.sleep import SleepConfig


@PreTrainedConfig.register_subclass("act_sr")
@dataclass
class ACTSRConfig(ACTConfig):
    """ACT with frozen actor memories, wake-time distillation and Nash-bargained sleep.

    Args (beyond ACT's):
        sleep: run the sleep phase after each skill k >= 2 (``false`` = the paper's "SR Wake-Only" ablation).
        distill_weight_second: gamma_2, wake distillation weight when learning the second skill.
        distill_weight_later: gamma_k for k >= 3.
        distill_batch_size: observations drawn from each earlier memory per wake step.
        distill_reduction: how a memory reduces the squared chunk difference over the chunk's elements: ``mean``
            (the "mean squared difference", on the per-element scale of ACT's l1 loss; default) or ``sum`` (the
            literal squared norm of the paper's equation, 112x larger for 16-step chunks of 7-d actions).
        memory_buffer_size: |B_k|, observations stored per skill memory.
        sleep_lr, sleep_max_iterations, sleep_batch_size: eta_sleep, N_sleep and the sleep batch per memory.
        sleep_early_stop_tol, sleep_early_stop_window: delta and the window of the plateau rule.
        sleep_fw_iterations: Frank-Wolfe iterations per solve of the ``nash_fw`` ablation (paper: 5); the default
            ``nash`` aggregator solves Eq. 1 exactly and ignores it.
        grad_norm_eps: eps of the per-skill l2 normalization.
        anchor_strength: lambda of the proximal sleep anchor toward the previous sleep checkpoint.
        anchor_tau: optional gate tau of Eq. 2 (``null``: always on, as in the SurgicAI setting).
        anchor_after_final: apply the anchor in the sleep after the last skill.
        aggregator: ``nash`` (the method, Eq. 1 solved exactly), ``nash_fw`` (the paper's Frank-Wolfe with
            ``sleep_fw_iterations``), ``mean_grad`` (the paper's Mean-grad ablation: raw-gradient mean),
            ``mean_normalized`` or ``pcgrad`` (see ``sr_imitation.core.aggregation``).
        use_images: ``false`` gives ACT's state-only mode: the state is also fed as
            ``observation.environment_state`` and no camera is used (the CPU preset's choice).
    """

    # ACT as in the paper.
    chunk_size: int = 16
    n_action_steps: int = 16
    latent_dim: int = 32
    kl_weight: float = 10.0
    vision_backbone: str = "resnet18"
    pretrained_backbone_weights: str | None = None  # nothing downloads at run time
    optimizer_lr: float = 1e-4
    optimizer_lr_backbone: float = 1e-5
    optimizer_weight_decay: float = 1e-4
    push_to_hub: bool = False

    # Sleeping Robots.
    sleep: bool = True
    distill_weight_second: float = 1.0
    distill_weight_later: float = 0.5
    distill_batch_size: int = 8
    distill_reduction: str = "mean"
    memory_buffer_size: int = 1024
    sleep_lr: float = 1e-5
    sleep_max_iterations: int = 1000
    sleep_batch_size: int = 8
    sleep_early_stop_tol: float = 1e-3
    sleep_early_stop_window: int = 50
    sleep_fw_iterations: int = 5
    grad_norm_eps: float = 1e-5
    anchor_strength: float = 1e-2
    anchor_tau: float | None = None
    anchor_after_final: bool = True
    aggregator: str = "nash"
    use_images: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        positive = {
            "distill_batch_size": self.distill_batch_size,
            "memory_buffer_size": self.memory_buffer_size,
            "sleep_lr": self.sleep_lr,
            "sleep_max_iterations": self.sleep_max_iterations,
            "sleep_batch_size": self.sleep_batch_size,
            "sleep_early_stop_window": self.sleep_early_stop_window,
            "sleep_fw_iterations": self.sleep_fw_iterations,
            "grad_norm_eps": self.grad_norm_eps,
        }
        bad = [f"{k}={v}" for k, v in positive.items() if not v > 0]
        non_negative = {
            "distill_weight_second": self.distill_weight_second,
            "distill_weight_later": self.distill_weight_later,
            "anchor_strength": self.anchor_strength,
            "sleep_early_stop_tol": self.sleep_early_stop_tol,
        }
        bad += [f"{k}={v}" for k, v in non_negative.items() if not v >= 0]  # NaN fails too
        if self.anchor_tau is not None and not self.anchor_tau > 0:
            bad.append(f"anchor_tau={self.anchor_tau}")
        if bad:
            raise ValueError(f"invalid ACT-SR settings: {', '.join(bad)}")
        if self.distill_reduction not in ("mean", "sum"):
            raise ValueError(f"distill_reduction must be 'mean' or 'sum', got {self.distill_reduction!r}")
        if self.aggregator not in AGGREGATORS:
            hint = " ('mean' was split into 'mean_grad' and 'mean_normalized')" if self.aggregator == "mean" else ""
            raise ValueError(f"aggregator must be one of {sorted(AGGREGATORS)}, got {self.aggregator!r}{hint}")

    def distill_weight(self, skill_number: int) -> float:
        """gamma_k of the wake objective for the k-th skill (1-based): 0, gamma_2, then gamma_later."""
        if skill_number < 1:
            raise ValueError(f"skill_number is 1-based, got {skill_number}")
        if skill_number == 1:
            return 0.0
        return self.distill_weight_second if skill_number == 2 else self.distill_weight_later

    def sleep_config(self, seed: int = 0) -> SleepConfig:
        """The core sleep settings for this policy."""
        return SleepConfig(
            lr=self.sleep_lr,
            max_iterations=self.sleep_max_iterations,
            batch_size=self.sleep_batch_size,
            aggregator=self.aggregator,
            fw_iterations=self.sleep_fw_iterations,
            eps=self.grad_norm_eps,
            early_stop_tol=self.sleep_early_stop_tol,
            early_stop_window=self.sleep_early_stop_window,
            anchor_strength=self.anchor_strength,
            anchor_tau=self.anchor_tau,
            anchor_after_final=self.anchor_after_final,
            seed=seed,
        )
