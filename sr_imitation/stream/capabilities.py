"""What a substrate offers continual methods beyond the :class:`~sr_imitation.stream.substrate.Substrate` protocol.

Each capability is a small runtime-checkable protocol. A method lists the ones it uses in
:attr:`ContinualMethod.requires <sr_imitation.stream.methods.base.ContinualMethod.requires>`; the engine refuses a
method whose substrate lacks one, in one line, when the run is built (before anything is written), and the method
reaches those members through :func:`capability`, typed. So a newcomer adding a method sees here what substrates
offer, and one adding a substrate sees what each method will ask of it.

==========================  ===========  =====================================================================
capability                  substrates   used by
==========================  ===========  =====================================================================
:class:`LikelihoodPolicy`   act, sac     EWC (Fisher information), Reset & Distill and Progress & Compress (theta)
:class:`PolicySnapshots`    act          LwF (the rolling teacher), M2Distill
:class:`IntermediateFeatures` act        M2Distill (feature distillation)
:class:`StoredDemonstrations` act        experience replay
:class:`ActorSnapshotMemory` act         Reset & Distill (the expert's memory where there is no Gaussian actor)
:class:`GaussianActor`      sac          DER, CLEAR, Reset & Distill (the paper's expert memory), Progress &
                                         Compress, SR's ``expert_memory`` option
:class:`StoredTransitions`  sac          CLEAR
:class:`ResettableNetworks` act, sac     Reset & Distill, Progress & Compress, SR's ``reset_wake`` option
:class:`ReplaceableActor`   sac          CompoNet
==========================  ===========  =====================================================================

A method may also require one of several capabilities: an entry ``X | Y`` of its ``requires`` (Reset & Distill's
``GaussianActor | ActorSnapshotMemory``) is met by a substrate that provides either.

Batches and samples are in the substrate's own layout (ACT: preprocessed LeRobot batches, dicts of tensors; SAC: raw
state tensors); a method passes them from one member to another without looking inside.
"""

from __future__ import annotations

import inspect
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, TypeVar, runtime_checkable

import torch
from torch import Tensor, nn

from sr_imitation.core.memory import Memory

Batch = Mapping[str, Tensor]
"""A training batch in the substrate's layout."""
Sample = Tensor | Sequence[Batch]
"""Inputs of a skill, one at a time: a tensor whose rows are states (SAC) or single-frame batches (ACT)."""


@runtime_checkable
class LikelihoodPolicy(Protocol):
    """A stochastic policy's log-likelihood and samples of a skill's inputs (the Fisher information of EWC)."""

    def policy_parameters(self) -> Sequence[Tensor]:
        """theta, the deployed policy's trainable parameters (in the sleep's order)."""

    def state_sample(self, k: int, n: int) -> Sample:
        """``n`` inputs of skill ``k``, seeded per stage."""

    def log_likelihood(self, sample: Tensor | Batch, generator: torch.Generator) -> Tensor:
        """log pi_theta(a | s) of an action drawn from (SAC) or demonstrated to (ACT) the policy, per input of
        ``sample``, differentiable in theta."""


@runtime_checkable
class ChunkTeacher(Protocol):
    """A frozen copy of the policy, as :meth:`PolicySnapshots.frozen_policy` returns it."""

    def action_chunk(self, batch: Batch) -> Tensor:
        """The deployed action chunk on a preprocessed batch."""

    def action_chunk_and_features(self, batch: Batch) -> tuple[Tensor, dict[str, Tensor]]:
        """:meth:`action_chunk` with the encoder's intermediate features."""


@runtime_checkable
class PolicySnapshots(Protocol):
    """Frozen copies of the current policy and its outputs (LwF's teacher)."""

    def frozen_policy(self) -> ChunkTeacher:
        """A frozen copy of the policy as it is now (building it leaves the random state alone)."""

    def policy_weights(self) -> dict[str, Tensor]:
        """Every tensor of the policy's state (what a frozen copy holds; the memory budget counts it)."""

    def chunk_policy(self, batch: Batch) -> Tensor:
        """The current policy's action chunk on a training batch."""


@runtime_checkable
class IntermediateFeatures(Protocol):
    """The current policy's intermediate features next to its output (M2Distill's multi-level targets)."""

    def chunk_and_features(self, batch: Batch) -> tuple[Tensor, dict[str, Tensor]]:
        """The action chunk and the named intermediate features on a training batch."""


@runtime_checkable
class StoredDemonstrations(Protocol):
    """Demonstration frames of a skill as a wake batch holds them (experience replay's stored frames)."""

    def demonstration_frames(self, k: int, n: int | None = None) -> dict[str, Tensor]:
        """``n`` frames of skill ``k`` (default: as many as a memory stores), seeded per stage."""


@runtime_checkable
class ActorSnapshotMemory(Protocol):
    """The substrate's own memory M_k is an actor snapshot: stored inputs of skill k and the policy's outputs on them
    when the memory was made; its sleep problem distils the deployed policy's outputs towards such memories (SR's ACT
    memory, and Reset & Distill's expert memory where there is no Gaussian actor)."""

    def actor_memory(self, k: int) -> Memory:
        """M_k of the current policy, frozen now and saved as the substrate's memory of skill ``k`` (what
        :meth:`~sr_imitation.stream.substrate.Substrate.make_memory` makes: ACT, the policy's action chunks on
        ``--memory.buffer_size`` stored frames of the skill)."""


@runtime_checkable
class GaussianActor(Protocol):
    """A Gaussian actor's outputs on raw states and the states a skill's memory keeps (DER's targets)."""

    def gaussian_policy(self, states: Tensor) -> Tensor:
        """[mean, log std] of the actor's pre-tanh Gaussian on raw ``states`` (B x 2A)."""

    def memory_states(self, k: int) -> Tensor:
        """The late-wake states of skill ``k`` the substrate's memory holds."""


@runtime_checkable
class StoredTransitions(Protocol):
    """Transitions sampled from a skill's replay when its wake ended (CLEAR)."""

    def transition_sample(self, k: int) -> dict[str, Tensor]:
        """Transitions of wake ``k`` (``obs``, ``actions``, ``rewards``, ``next_obs``, ``terminated``)."""


@runtime_checkable
class ResettableNetworks(Protocol):
    """Fresh networks per skill and the actor of an earlier checkpoint (Reset & Distill, Progress & Compress)."""

    def reset_networks(self, k: int) -> None:
        """Freshly initialized networks for skill ``k``, seeded from (run seed, k); the global random state is left
        as it was (SAC: actor, critics and temperature; ACT: the whole policy)."""

    def load_actor(self, k: int, phase: str) -> None:
        """Only the actor of the checkpoint after ``phase`` of stage ``k`` (SAC: not the critics; ACT: the policy's
        weights, in the statistics in use)."""


@runtime_checkable
class ReplaceableActor(Protocol):
    """An actor a method may replace by its own architecture, and a critic it may reset (CompoNet)."""

    def replace_actor(self, build: Callable[..., nn.Module]) -> None:
        """Put ``build(policy_config, n_skills)`` in place of the actor (seeded; fresh optimizers)."""

    def current_actor(self) -> nn.Module:
        """The actor the substrate trains now."""

    def reset_critic(self, k: int) -> None:
        """A freshly initialized critic for skill ``k``, seeded from (run seed, k)."""


C = TypeVar("C")


def capability[C](substrate: object, required: type[C]) -> C:
    """``substrate`` as the capability ``required`` (a protocol of this module); ``TypeError`` naming both if it
    lacks it (the engine has refused such a method already: this guards direct use)."""
    if not isinstance(substrate, required):
        raise TypeError(f"{type(substrate).__name__} does not provide {required.__name__} "
                        f"({', '.join(protocol_members(required))})")
    return substrate


def protocol_members(protocol: type) -> list[str]:
    """The public members a protocol declares: its methods and properties, and its annotated attributes (``name:
    ClassVar[str]``, which have no value in the class)."""
    names = set(vars(protocol).get("__annotations__", {})) | set(vars(protocol))
    return sorted(name for name in names if not name.startswith("_"))


def missing_members(obj: object, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``obj`` (an instance or a class) lacks, found without calling anything (a
    property is not evaluated)."""
    return [name for name in protocol_members(protocol) if inspect.getattr_static(obj, name, _ABSENT) is _ABSENT]


_ABSENT = object()


def alternatives(requirement: Any) -> tuple[type, ...]:
    """The capabilities a ``requires`` entry accepts: ``(X,)`` for a capability X, ``(X, Y)`` for ``X | Y`` (either
    meets it)."""
    return typing.get_args(requirement) or (requirement,)


def requirement_name(requirement: Any) -> str:
    """A ``requires`` entry by name: ``X``, or ``either X or Y`` for ``X | Y``."""
    names = [c.__name__ for c in alternatives(requirement)]
    return names[0] if len(names) == 1 else f"either {' or '.join(names)}"


def missing_capabilities(substrate: object, required: Sequence[Any]) -> list[str]:
    """The names (:func:`requirement_name`) of the entries of ``required`` that ``substrate`` (an instance or a class)
    does not meet: a capability it lacks, or a union ``X | Y`` none of whose capabilities it provides."""
    return [requirement_name(c) for c in required if all(missing_members(substrate, a) for a in alternatives(c))]
