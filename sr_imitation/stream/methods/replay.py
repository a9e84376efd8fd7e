"""Experience replay (ER; Chaudhry et al., 2019, "On Tiny Episodic Memories in Continual Learning") as LIBERO's ER
baseline (Liu et al., 2023, LIBERO, ``libero/lifelong/algos/er.py``): behaviour cloning on stored demonstration
frames of earlier skills, mixed into every wake batch.

After each skill i's wake: a buffer R_i of N = ``--memory.buffer_size`` demonstration frames of the skill (as many
as SR's memory M_i stores: the default 1024, 16 in ``configs/needle_cpu_m16.json``), each as a wake batch holds it:
the normalized policy inputs (state; images as normalized float), the normalized target action chunk and its
``action_is_pad`` mask. The frames are those M_i buffers (the same seeded draw, uniform over all the skill's
demonstration frames, its training and validation episodes alike, without replacement; our choice: LIBERO's
``TruncatedSequenceDataset`` keeps the task dataset's first ``n_memories`` samples, i.e. the first demonstrations'
opening frames). A skill with fewer than N frames stores N draws with replacement, so every buffer holds exactly N
frames, as every SR memory does (our choice).

At every update of wake k > 1 the batch is the current skill's batch B_k (size b) concatenated with b frames drawn
uniformly with replacement from the union R_1 u ... u R_{k-1} (LIBERO: a batch of the training batch size from the
concatenated buffers; with replacement is our choice), drawn with the wake's generator (seeded per stage), and ACT's
own loss (masked l1 on the chunk plus the VAE's KL) is taken over the 2b frames:

    L = ACT( B_k  ++  B_replay ),    B_replay ~ U(R_1 u ... u R_{k-1})^b.

Nothing else: no distillation (gamma_k = 0), no sleep. The replayed frames come only from the stored buffers, never
from the datasets of earlier skills. The first skill's wake is plain behaviour cloning.

Memory per skill: N x (state + chunk x action_dim) float32 + N x chunk bool, i.e. SR's M_i (observations and
action chunks of the same shapes) plus the padding mask. With images the buffer holds them as normalized float32,
4x the bytes of SR's uint8 images (``memory.md`` reports the stored bytes).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.core.memory import Memory, register_memory
from sr_imitation.stream.capabilities import StoredDemonstrations, capability
from sr_imitation.stream.methods.base import ContinualMethod, WakeStep
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate

ACTION, PAD = "action", "action_is_pad"


@dataclass(frozen=True)
class ReplayConfig:
    replay_ratio: float = 1.0
    """Replayed frames per update as a multiple of the current skill's batch size (1: as many, LIBERO's ER)."""

    def __post_init__(self) -> None:
        if not self.replay_ratio > 0:
            raise ValueError(f"replay_ratio must be > 0, got {self.replay_ratio}")


@register_memory
class DemonstrationMemory(Memory):
    """Demonstration frames of one skill as a wake batch holds them: normalized inputs, the normalized target action
    chunk (``action``) and its padding mask (``action_is_pad``). :meth:`loss` is the masked l1 behaviour-cloning error
    of a chunk policy on a batch of them (a diagnostic: the wake trains on the substrate's own loss)."""

    kind = "act_demonstrations"
    contents = "demonstration frames (normalized observations + target action chunks and padding masks)"

    @property
    def buffer_keys(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(sorted(self.tensors))

    def _validate(self) -> None:
        missing = {ACTION, PAD} - set(self.tensors)
        if missing or len(self.tensors) < 3:
            raise ValueError(f"DemonstrationMemory({self.skill!r}) needs inputs, {ACTION!r} and {PAD!r} "
                             f"(missing {sorted(missing)})")
        if self.tensors[PAD].dtype != torch.bool or self.tensors[PAD].shape != self.tensors[ACTION].shape[:2]:
            raise ValueError(f"DemonstrationMemory({self.skill!r}): {PAD!r} must be a bool mask of the chunk")
        super()._validate()

    def loss(self, policy: Any, batch: Mapping[str, Tensor]) -> Tensor:
        pred = policy(batch)
        keep = (~batch[PAD].to(pred.device)).unsqueeze(-1)
        return ((pred - batch[ACTION].to(pred)).abs() * keep).mean()


def concat_replay(memories: list[Memory]) -> dict[str, Tensor]:
    """The union R_1 u ... u R_{k-1} of the stored buffers, one tensor per key (frames of R_1 first)."""
    keys = memories[0].buffer_keys
    for m in memories[1:]:
        if m.buffer_keys != keys:
            raise ValueError(f"replay buffers hold different keys: {keys} vs {m.buffer_keys} ({m.skill!r})")
    return {key: torch.cat([m.tensors[key] for m in memories]) for key in keys}


@register_method
class ExperienceReplay(ContinualMethod):
    """Behaviour cloning on stored demonstration frames of earlier skills, mixed into every wake batch."""

    name = "replay"
    resumable_wake_hooks = True  # nothing carried from one update to the next
    requires = (StoredDemonstrations,)
    stores_memories = True
    memory_name = "replay"
    config: ClassVar[ReplayConfig] = ReplayConfig()

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self.pool = concat_replay(self.memories) if self.memories else None

    def replay_indices(self, size: int, generator: torch.Generator | None) -> Tensor:
        """Indices into the union of the stored buffers for one update with a current batch of ``size`` frames."""
        assert self.pool is not None
        total = len(self.pool[ACTION])
        n = max(1, int(round(self.config.replay_ratio * size)))
        return torch.randint(total, (n,), generator=generator)

    def wake_batch(self, step: WakeStep) -> Mapping[str, Tensor]:
        """The current skill's batch followed by the replayed frames, with the keys the buffers store (what ACT
        trains on; the batch's other entries are dropped); the current batch unchanged before any skill is stored."""
        if self.pool is None:
            return step.batch
        missing = set(self.pool) - set(step.batch)
        if missing:
            raise ValueError(f"replay: the wake batch lacks the stored keys {sorted(missing)}")
        current = {key: step.batch[key] for key in self.pool}
        idx = self.replay_indices(len(current[ACTION]), step.generator)
        return {key: torch.cat([value, self.pool[key][idx].to(value.device, value.dtype)])
                for key, value in current.items()}

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        """R_k: ``--memory.buffer_size`` frames of skill k (``ACTSubstrate.demonstration_frames``), saved checked."""
        frames = capability(substrate, StoredDemonstrations).demonstration_frames(k)
        return self.save_memory(k, substrate, DemonstrationMemory(substrate.memory_skill(k), frames))
