"""ACT-SR policy: LeRobot's ACT with wake-time distillation from frozen actor memories (paper Eq. L_wake).

L_wake = L_BC + gamma_k sum_{i<k} E_{o ~ B_i} ||pi_theta(o) - pi_{theta_i^wake}(o)||^2, where L_BC is ACT's own loss
(masked L1 on the action chunk + KL weight x KL) and pi(o) is the deterministic action chunk (zero latent, no
dropout) in the stream's fixed normalized action space. Memories are attached by the stream trainer with
:meth:`ACTSRPolicy.set_wake_memories`; without memories the policy trains exactly like ACT, so stock
``lerobot-train --policy.type=act_sr`` works on a single dataset.

Memories are kept in a plain list, outside the ``nn.Module`` tree: they are not saved in ``model.safetensors``,
not moved by ``.to()`` and never trained; they have their own files (``memories/skill_k.safetensors``).

``--policy.sleep=true`` on stock ``lerobot-train`` (the design card's command): the policy keeps a uniform reservoir
(:class:`ObservationReservoir`) of the observations it trains on and every ``save_pretrained`` writes the skill's
frozen actor memory M_k^pi = (pi_{theta_k^wake}, B_k) (Section 3) beside ``model.safetensors`` as
:data:`MEMORY_FILE`, in the stream's format (:class:`~lerobot_policy_act_sr.actor_memory.ActorMemory`, loaded by
:func:`sr_imitation.core.memory.load_memory`), so a skill trained with stock ``lerobot-train`` can later be
consolidated in a sleep. With ``sleep`` false or not given nothing of this exists and training is ACT-SR's as before.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.processor.normalize_processor import NormalizerProcessorStep, UnnormalizerProcessorStep
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor
from torchvision.ops.misc import FrozenBatchNorm2d

from lerobot_policy_act_sr.actor_memory import ActorMemory, images_to_uint8
from lerobot_policy_act_sr.configuration_act_sr import ACTSRConfig
from sr_imitation.core.memory import Memory, summed_objective

logger = logging.getLogger(__name__)

ObservationNormalizer = Callable[[Mapping[str, Tensor]], dict[str, Tensor]]

TRAINING_ONLY_PREFIXES = ("model.vae_encoder",)
"""Parameters of modules only the training forward uses: ACT's VAE encoder (its CLS embedding, input projections,
transformer and latent output projection) infers the style latent from the demonstration's actions; at inference
the latent is zero and the encoder is never run. Sleep optimizes the deployed policy only (our choice, because
in sleep these parameters would receive no memory gradient, only the anchor pull, and would inflate the gate distances
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


MEMORY_FILE = "memory.safetensors"
"""The frozen actor memory ``--policy.sleep=true`` writes beside a checkpoint's ``model.safetensors``."""

RESERVOIR_SEED = 0
"""Seed of the reservoir's draws (our choice). The draws depend only on how many observations came before, not on
their values, so runs with the same batch sizes keep the same positions of the observation stream."""

MEMORY_SNAPSHOT = "."
"""``config["snapshot"]`` of a memory written beside its checkpoint: the snapshot's weights are the directory that
holds the memory file (the stream's memories name their stage checkpoint relative to the run instead)."""


class ObservationReservoir:
    """A uniform sample of at most ``size`` observations from a stream of batches (reservoir sampling, Vitter's
    Algorithm R): after n observations each of them is held with probability min(1, size / n).

    Tensors are kept on the CPU with the dtype they arrive in; the first batch fixes the keys and shapes.
    """

    def __init__(self, size: int, seed: int = RESERVOIR_SEED) -> None:
        if size < 1:
            raise ValueError(f"reservoir size must be >= 1, got {size}")
        self.size = int(size)
        self.seen = 0
        self._buffers: dict[str, Tensor] = {}
        self._generator = torch.Generator().manual_seed(seed)

    def __len__(self) -> int:
        return min(self.seen, self.size)

    def add(self, batch: Mapping[str, Tensor]) -> None:
        """Offer every row of ``batch`` (tensors sharing their first dimension) to the reservoir, in order."""
        if not batch:
            return
        if not self._buffers:
            self._buffers = {k: torch.zeros((self.size, *v.shape[1:]), dtype=v.dtype) for k, v in batch.items()}
        elif set(batch) != set(self._buffers):
            raise ValueError(f"reservoir holds {sorted(self._buffers)}, got a batch of {sorted(batch)}")
        slots: dict[int, int] = {}  # slot -> row; a later row for the same slot replaces an earlier one
        for row in range(int(next(iter(batch.values())).shape[0])):
            self.seen += 1
            if self.seen <= self.size:
                slots[self.seen - 1] = row
                continue
            slot = int(torch.randint(self.seen, (1,), generator=self._generator))
            if slot < self.size:
                slots[slot] = row
        if slots:
            where = torch.tensor(list(slots))
            rows = torch.tensor(list(slots.values()))
            for key, buffer in self._buffers.items():
                buffer[where] = batch[key].detach()[rows.to(batch[key].device)].to("cpu", buffer.dtype)

    def observations(self) -> dict[str, Tensor]:
        """The held observations (copies), ``len(self)`` rows each."""
        return {k: v[: len(self)].clone() for k, v in self._buffers.items()}


def state_only_features(config: ACTSRConfig) -> None:
    """ACT's state-only mode (``use_images=false``) on ``config.input_features``: cameras dropped, the state also
    declared as ``observation.environment_state`` (ACT needs an image or an environment state; the policy copies
    the normalized state there). ``sr-train`` declares the features this way itself; stock ``lerobot-train`` fills
    them from the dataset, cameras included, so without this the camera was still used (11.2M parameters instead
    of 25k). Idempotent."""
    inputs = {k: f for k, f in (config.input_features or {}).items() if f.type is not FeatureType.VISUAL}
    if OBS_STATE in inputs and OBS_ENV_STATE not in inputs:
        inputs[OBS_ENV_STATE] = PolicyFeature(type=FeatureType.ENV, shape=inputs[OBS_STATE].shape)
    config.input_features = inputs


class ACTSRPolicy(ACTPolicy):
    """ACT + Sleeping Robots (the policy class LeRobot's factory finds for ``act_sr``)."""

    config_class = ACTSRConfig
    name = "act_sr"

    def __init__(self, config: ACTSRConfig, **kwargs: Any) -> None:
        if not config.use_images and config.input_features:
            state_only_features(config)  # stock lerobot-train fills the features from the dataset, cameras included
        super().__init__(config, **kwargs)
        self.config: ACTSRConfig = config
        if config.image_features and config.resolved_backbone_norm == "group":
            group_norm_backbone(self.model.backbone)
        self._wake_memories: list[Memory] = []
        self._distill_weight = 0.0
        self._normalize_observation: ObservationNormalizer | None = None
        self._memory_generator = torch.Generator()
        # --policy.sleep=true (stock lerobot-train): the reservoir and what turns its observations back to raw.
        if config.sleep_memory_size is not None and not config.sleep:
            # Checked here, not in ACTSRConfig: sr-train folds both into its own settings after building the config.
            raise ValueError("policy.sleep_memory_size sizes the memory that policy.sleep=true writes; give "
                             "--policy.sleep=true with it")
        self._reservoir = ObservationReservoir(config.resolved_sleep_memory_size) if config.sleep else None
        self._dataset_stats = kwargs.get("dataset_stats")
        self._normalizers: tuple[NormalizerProcessorStep, UnnormalizerProcessorStep] | None = None
        self._memory_skill = str(getattr(kwargs.get("dataset_meta"), "repo_id", "") or "skill")

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
    def memory_generator(self) -> torch.Generator:
        """The generator the wake's distillation term draws its memory frames from (seeded by
        :meth:`set_wake_memories`): part of what a mid-wake snapshot keeps."""
        return self._memory_generator

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

    # -- --policy.sleep=true: the skill's frozen memory -------------------------------------------------
    @property
    def reservoir(self) -> ObservationReservoir | None:
        """The observations kept for the skill's memory (``None`` unless ``config.sleep``)."""
        return self._reservoir

    def _normalizer_steps(self) -> tuple[NormalizerProcessorStep, UnnormalizerProcessorStep]:
        """LeRobot's observation normalizer and its inverse with the dataset statistics the policy was built with
        (``make_policy`` passes the same ``dataset.meta.stats`` that ``lerobot-train``'s preprocessor uses)."""
        if not self._dataset_stats:
            raise ValueError("policy.sleep=true keeps the raw observations it trains on and needs the dataset "
                             "statistics for that: build the policy with make_policy(cfg, ds_meta=...) as "
                             "lerobot-train does")
        if self._normalizers is None:
            args = {"features": dict(self.config.input_features), "norm_map": self.config.normalization_mapping,
                    "stats": self._dataset_stats}
            self._normalizers = NormalizerProcessorStep(**args), UnnormalizerProcessorStep(**args)
        return self._normalizers

    def _remember(self, batch: Mapping[str, Tensor]) -> None:
        """Offer the batch's observations, turned back into the dataset's raw values (images as uint8), to the
        reservoir: the memory stores raw observations, as the stream's memories do."""
        keys = [k for k in self.config.input_features if k in batch]
        with torch.no_grad():
            raw = self._normalizer_steps()[1]._normalize_observation({k: batch[k].detach() for k in keys},
                                                                      inverse=True)
        images = set(self.config.image_features)
        self._reservoir.add({k: images_to_uint8(raw[k]) if k in images else raw[k].float() for k in keys})

    def frozen_memory(self, batch_size: int = 64) -> ActorMemory | None:
        """M_k^pi = (pi_theta, B_k) of this policy now: the reservoir's observations and this policy's action chunks
        on them (normalized as the training batches were), in the stream's actor-memory format with
        ``reduction = config.distill_reduction``. ``None`` before any training observation."""
        if self._reservoir is None or len(self._reservoir) == 0:
            return None
        normalize = self._normalizer_steps()[0]
        device = next(self.parameters()).device

        def chunk(raw: Mapping[str, Tensor]) -> Tensor:
            obs = {k: (v.float() / 255.0 if v.dtype == torch.uint8 else v).to(device) for k, v in raw.items()}
            return self.action_chunk(normalize._normalize_observation(obs, inverse=False))

        return ActorMemory.from_observations(self._memory_skill, chunk, self._reservoir.observations(),
                                             snapshot=MEMORY_SNAPSHOT, batch_size=batch_size,
                                             reduction=self.config.distill_reduction)

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """LeRobot's checkpoint (``state_dict``: a pre-gathered one, as LeRobot passes it), plus :data:`MEMORY_FILE`
        when ``config.sleep`` (see :meth:`frozen_memory`)."""
        super()._save_pretrained(save_directory, state_dict=state_dict)
        if self._reservoir is None:
            return
        memory = self.frozen_memory()
        if memory is None:
            logger.warning("policy.sleep=true: no training observations yet, so %s has no %s", save_directory,
                           MEMORY_FILE)
            return
        memory.save(Path(save_directory) / MEMORY_FILE)
        logger.info("policy.sleep=true: wrote the frozen actor memory of %r (%d of %d observations seen) to %s",
                    memory.skill, memory.size, self._reservoir.seen, Path(save_directory) / MEMORY_FILE)

    # -- LeRobot API -------------------------------------------------------------------------------
    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        self.eval()
        return self.model(self._model_batch(batch))[0]

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """ACT's loss plus gamma_k times the summed distillation losses of the attached memories. With
        ``config.sleep``, training batches' observations are also offered to the reservoir."""
        if self._reservoir is not None and self.training:
            self._remember(batch)
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
