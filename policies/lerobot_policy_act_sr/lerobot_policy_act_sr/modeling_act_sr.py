"""ACT-SR policy: LeRobot's ACT with wake-time distillation from frozen actor memories (paper Eq. L_wake).

L_wake = L_BC + gamma_k sum_{i<k} E_{o ~ B_i} ||pi_theta(o) - pi_{theta_i^wake}(o)||^2, where L_BC is ACT's own loss
(masked L1 on the action chunk + KL weight x KL) and pi(o) is the deterministic action chunk (zero latent, no
dropout) in the stream's fixed normalized action space. Memories are attached by the stream trainer with
:meth:`ACTSRPolicy.set_wake_memories`; without memories the policy trains exactly like ACT, so stock
``lerobot-train --policy.type=act_sr`` works on a single dataset.

Memories are kept in a plain list, outside the ``nn.Module`` tree: they are not saved in ``model.safetensors``,
not moved by ``.to()`` and never trained; they have their own files (``memories/skill_k.safetensors``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor
from torchvision.ops.misc import FrozenBatchNorm2d

from lerobot_policy_act_sr.configuration_act_sr import ACTSRConfig
from sr_imitation.core.memory import Memory, summed_objective

ObservationNormalizer = Callable[[Mapping[str, Tensor]], dict[str, Tensor]]

TRAINING_ONLY_PREFIXES = ("model.vae_encoder",)
"""Parameters of modules only the training forward uses: ACT's VAE encoder (its CLS embedding, input projections,
transformer and latent output projection) infers the style latent from the demonstration's actions; at inference
the latent is zero and the encoder is never run. Sleep optimizes the deployed policy only (our choice, issue 10:
in sleep these parameters received no memory gradient, only the anchor pull, and they inflated the gate distances
c_i of Eq. 2)."""


FEATURE_MODULES: dict[str, str] = {
    "encoder_robot_state_input_proj": "robot_state",
    "encoder_env_state_input_proj": "env_state",
    "backbone": "camera",
    "encoder": "encoder",
}
"""ACT submodules whose outputs :meth:`ACTSRPolicy.action_chunk_and_features` returns, and their feature names."""


GROUP_NORM_CHANNELS = 16
"""Channels per group of the ``group`` backbone normalization (ResNet-18's 64..512 channels: 4..32 groups)."""


def group_norm_backbone(backbone: torch.nn.Module) -> int:
    """Replace every ``FrozenBatchNorm2d`` of ``backbone`` (in place) by a trainable ``GroupNorm`` over the same
    channels with :data:`GROUP_NORM_CHANNELS` channels per group (weight 1, bias 0, no random draw); returns how
    many were replaced. See :attr:`ACTSRConfig.backbone_norm` for why."""
    replaced = 0
    for parent in list(backbone.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, FrozenBatchNorm2d):
                channels = child.weight.numel()
                setattr(parent, name, torch.nn.GroupNorm(max(1, channels // GROUP_NORM_CHANNELS), channels))
                replaced += 1
    return replaced


class ACTSRPolicy(ACTPolicy):
    """ACT + Sleeping Robots (the policy class LeRobot's factory finds for ``act_sr``)."""

    config_class = ACTSRConfig
    name = "act_sr"

    def __init__(self, config: ACTSRConfig, **kwargs: Any) -> None:
        super().__init__(config, **kwargs)
        self.config: ACTSRConfig = config
        if config.image_features and config.resolved_backbone_norm == "group":
            group_norm_backbone(self.model.backbone)
        self._wake_memories: list[Memory] = []
        self._distill_weight = 0.0
        self._normalize_observation: ObservationNormalizer | None = None
        self._memory_generator = torch.Generator()

    def deployed_named_parameters(self) -> list[tuple[str, torch.nn.Parameter]]:
        """The trainable parameters of the deployed policy (inference forward), in module order: everything but
        :data:`TRAINING_ONLY_PREFIXES`. What sleep optimizes and anchors, and what the gates measure."""
        return [(n, p) for n, p in self.named_parameters()
                if p.requires_grad and not n.startswith(TRAINING_ONLY_PREFIXES)]

    # -- memories ----------------------------------------------------------------------------------
    def set_observation_normalizer(self, normalize: ObservationNormalizer) -> None:
        """Set the function that turns raw buffered observations into normalized model inputs.

        The stream trainer passes the (fixed) preprocessor here, so that memory buffers, which store raw
        observations, are normalized exactly as the dataset batches are.
        """
        self._normalize_observation = normalize

    def set_wake_memories(self, memories: Sequence[Memory], weight: float, seed: int = 0) -> None:
        """Attach the frozen memories of earlier skills and gamma_k for the wake objective."""
        if memories and self._normalize_observation is None:
            raise RuntimeError("call set_observation_normalizer() before attaching memories")
        if weight < 0:
            raise ValueError(f"distillation weight must be >= 0, got {weight}")
        self._wake_memories = list(memories)
        self._distill_weight = float(weight)
        self._memory_generator = torch.Generator().manual_seed(seed)

    @property
    def wake_memories(self) -> list[Memory]:
        return list(self._wake_memories)

    # -- inputs --------------------------------------------------------------------------------------
    def _model_batch(self, batch: Mapping[str, Tensor]) -> dict[str, Any]:
        """Shallow copy with ACT's image list and, in state-only mode, the state as environment state."""
        out = dict(batch)
        if self.config.env_state_feature and OBS_ENV_STATE not in out and OBS_STATE in out:
            out[OBS_ENV_STATE] = out[OBS_STATE]
        if self.config.image_features:
            out[OBS_IMAGES] = [out[key] for key in self.config.image_features]
        return out

    def action_chunk(self, batch: Mapping[str, Tensor]) -> Tensor:
        """pi_theta(o): the deterministic action chunk (zero latent, no dropout), differentiable.

        ``batch`` holds normalized observations; returns (B, chunk_size, action_dim), normalized.
        """
        model_batch = self._model_batch({k: v for k, v in batch.items() if k != ACTION})
        was_training = self.model.training
        self.model.eval()  # zero-latent branch and no dropout; gradients still flow
        try:
            return self.model(model_batch)[0]
        finally:
            self.model.train(was_training)

    def action_chunk_and_features(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """:meth:`action_chunk` with the intermediate features M2Distill distills (one forward pass).

        Features, each (tokens, B, D) or (B, ...): every input modality's embedding - ``robot_state`` and
        ``env_state`` (the state tokens' input projections), ``camera<i>`` (camera i's backbone feature map) - and
        ``encoder`` (the transformer encoder's output tokens, the latent the decoder reads).
        """
        features: dict[str, Tensor] = {}
        cameras: list[Tensor] = []

        def keep(key: str) -> Callable[..., None]:
            def hook(_module: Any, _inputs: Any, out: Any) -> None:
                if key == "camera":
                    cameras.append(out["feature_map"])  # the backbone runs once per camera
                else:
                    features[key] = out
            return hook

        handles = [module.register_forward_hook(keep(key)) for name, key in FEATURE_MODULES.items()
                   if (module := getattr(self.model, name, None)) is not None]
        try:
            chunk = self.action_chunk(batch)
        finally:
            for handle in handles:
                handle.remove()
        features.update({f"camera{i}": f for i, f in enumerate(cameras)})
        return chunk, features

    def memory_chunk(self, raw_observations: Mapping[str, Tensor]) -> Tensor:
        """pi_theta on raw buffered observations (what memories evaluate)."""
        if self._normalize_observation is None:
            raise RuntimeError("no observation normalizer set; call set_observation_normalizer() first")
        return self.action_chunk(self._normalize_observation(raw_observations))

    # -- LeRobot API -------------------------------------------------------------------------------
    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        self.eval()
        return self.model(self._model_batch(batch))[0]

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """ACT's loss plus gamma_k times the summed distillation losses of the attached memories."""
        batch = dict(batch)
        if self.config.env_state_feature and OBS_ENV_STATE not in batch and OBS_STATE in batch:
            batch[OBS_ENV_STATE] = batch[OBS_STATE]
        loss, loss_dict = super().forward(batch)
        if self._wake_memories and self._distill_weight > 0.0:
            distill = summed_objective(self._wake_memories, self.memory_chunk, self.config.distill_batch_size,
                                       self._memory_generator)
            loss = loss + self._distill_weight * distill
            loss_dict["distill_loss"] = float(distill.detach())
        loss_dict["bc_loss"] = loss_dict["l1_loss"] + self.config.kl_weight * loss_dict.get("kld_loss", 0.0)
        if not torch.isfinite(loss):
            # Raised before any backward pass, so a NaN never reaches the weights.
            raise FloatingPointError(f"non-finite ACT-SR loss {float(loss.detach())} (components {loss_dict})")
        return loss, loss_dict
