"""The continual-method plugin interface (in the spirit of Continual World's and Avalanche's hooks).

A method answers, per skill:

* what its wake adds: :meth:`ContinualMethod.wake_memories` (distillation from memories at gamma_k, the substrate's
  own wake term, ACT), :meth:`~ContinualMethod.wake_loss` (an auxiliary loss on every policy update: EWC's penalty,
  DER's distillation) and :meth:`~ContinualMethod.adjust_gradients` (a change of the policy gradient after the
  backward pass: A-GEM's projection, PCGrad, Nash-MTL), both on the :class:`WakeStep` the substrate's wake loop hands
  it at each policy update;
* what it keeps after the wake: :meth:`~ContinualMethod.make_memory` (default: the substrate's memory, what SR's
  sleep needs; EWC keeps a parameter snapshot and Fisher instead);
* whether it sleeps: :meth:`~ContinualMethod.sleeps_after`, and on which memories and problem
  (:meth:`~ContinualMethod.sleep_memories`, :meth:`~ContinualMethod.prepare_sleep`).

Everything else (data, wake loop, checkpoints, evaluation, metrics, resume) belongs to the engine and the substrate,
so a baseline is one file: subclass :class:`ContinualMethod`, decorate it with :func:`register_method`. A method's
state must come from files the run directory holds (its memories, the checkpoints), never from what happened
earlier in the process: a resumed run must compute the same numbers.
"""

from __future__ import annotations

import contextlib
import dataclasses
import typing
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from sr_imitation.core.memory import Memory
from sr_imitation.infra.snapshot import prefixed
from sr_imitation.infra.value_types import check_settings
from sr_imitation.stream.substrate import WAKE_HOOKS, MethodSettings, SleepProblem, Substrate


@dataclass
class WakeStep:
    """What a substrate's wake loop hands a method at every policy update.

    Attributes:
        stage: k, the 0-based index of the skill being learned.
        update: the number of policy updates already made in this wake (0 at the first).
        parameters: theta, the deployed policy's trainable parameters (those the sleep updates), whose ``.grad``
            :meth:`ContinualMethod.adjust_gradients` may change.
        policy: the current policy as the memories evaluate it (:meth:`Memory.loss`'s ``policy`` argument).
        batch: the update's batch of the current skill, in the substrate's layout (SAC: raw ``obs`` etc.).
        generator: the wake's generator for anything the method samples (memory batches), seeded per stage.
    """

    stage: int
    update: int
    parameters: Sequence[Tensor]
    policy: Any
    batch: Mapping[str, Tensor]
    generator: Any = None


class WakeHooks:
    """Hands a continual method's wake hooks a :class:`WakeStep` at every policy update of a substrate's wake loop:
    ``batch(batch)`` before the forward pass (the method's :meth:`~ContinualMethod.wake_batch`), ``loss(loss)``
    before the backward pass (:meth:`~ContinualMethod.wake_loss`), ``adjust()`` after it
    (:meth:`~ContinualMethod.adjust_gradients`; the numbers it returns are averaged in :meth:`summary`). One step
    object per update; memory batches come from a generator seeded by ``seed`` (per stage), so the hooks leave the
    random streams the substrate draws from alone; ``quiet`` wraps every hook (the SAC actor's activity recording
    is off while a method evaluates the actor)."""

    def __init__(self, method: ContinualMethod, stage: int, parameters: Sequence[Tensor], policy: Any, seed: int,
                 quiet: Callable[[], AbstractContextManager[Any]] = contextlib.nullcontext) -> None:
        self.method, self.stage, self.parameters, self.policy, self.quiet = method, stage, parameters, policy, quiet
        self.generator = torch.Generator().manual_seed(int(seed) % (2**31) + 17)
        self.updates = 0
        self.sums: dict[str, float] = {}
        self._step: WakeStep | None = None
        self.calls = dict.fromkeys(WAKE_HOOKS, 0)
        """How often the substrate's wake called each hook in this process; the engine checks them against the
        substrate's declared :attr:`~sr_imitation.stream.substrate.Substrate.wake_hooks` after the wake."""
        method.hook_calls = self.calls

    def batch(self, batch: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The batch this update trains on."""
        self.calls["wake_batch"] += 1
        self._step = WakeStep(self.stage, self.updates, self.parameters, self.policy, batch, self.generator)
        with self.quiet():
            self._step.batch = dict(self.method.wake_batch(self._step))
        return dict(self._step.batch)

    def loss(self, loss: Tensor) -> Tensor:
        """The loss the update differentiates."""
        assert self._step is not None, "WakeHooks.batch must be called first in every update"
        self.calls["wake_loss"] += 1
        with self.quiet():
            return self.method.wake_loss(loss, self._step)

    def adjust(self) -> None:
        """After the backward pass, before clipping and the optimizer step."""
        assert self._step is not None, "WakeHooks.batch must be called first in every update"
        self.calls["adjust_gradients"] += 1
        with self.quiet():
            values = self.method.adjust_gradients(self._step)
        for key, value in values.items():
            self.sums[key] = self.sums.get(key, 0.0) + float(value)
        self.updates += 1

    @property
    def resumable(self) -> bool:
        """Whether a mid-wake snapshot can carry these hooks (:attr:`ContinualMethod.resumable_wake_hooks`)."""
        return self.method.resumable_wake_hooks

    def state(self) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """What the hooks carry between updates, as tensors and a JSON record: the generator's state (tensor
        ``generator``), the update count and sums, and the method's own :meth:`~ContinualMethod.wake_state`
        (tensors ``method.<name>``, record ``method``)."""
        method_tensors, method_record = self.method.wake_state()
        tensors = {"generator": self.generator.get_state(), **{f"method.{n}": t for n, t in method_tensors.items()}}
        return tensors, {"updates": self.updates, "sums": dict(self.sums), "method": method_record}

    def load_state(self, tensors: Mapping[str, Tensor], record: Mapping[str, Any]) -> None:
        """Restore what :meth:`state` returned (after the method's :meth:`~ContinualMethod.begin_wake`)."""
        self.generator.set_state(tensors["generator"])
        self.updates, self.sums = int(record["updates"]), dict(record["sums"])
        self.method.load_wake_state(prefixed(dict(tensors), "method."), record.get("method", {}))

    def summary(self) -> dict[str, float]:
        """The mean over updates of every number :meth:`~ContinualMethod.adjust_gradients` returned."""
        return {key: value / max(1, self.updates) for key, value in sorted(self.sums.items())}


def with_options(method: str, config: Any, options: Mapping[str, Any]) -> Any:
    """``config`` (a method's frozen settings dataclass) with ``options`` replacing fields of the same name;
    ``ValueError`` naming ``method_options`` and the valid names for anything else, or naming the option and its
    value for a value that is not the option's type (a number given a boolean, null or text, a boolean a number:
    :func:`~sr_imitation.infra.value_types.check_settings`)."""
    names = [f.name for f in dataclasses.fields(config)] if dataclasses.is_dataclass(config) else []
    unknown = sorted(set(options) - set(names))
    if unknown:
        raise ValueError(f"method_options: {method!r} has no option(s) {unknown}; its options: {names or 'none'}")
    options = _as_option_numbers(type(config), options)
    check_settings(type(config), options, "method_options", text_numbers=False)  # nothing converts an option's text
    return dataclasses.replace(config, **options)


def _as_option_numbers(config_class: type, options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` with each number as its option's kind: ``--method_options`` is read as ``bool | float | str``
    (the command line's ``{iterations: 3}`` arrives as 3.0), so a whole float becomes an ``int`` option's integer
    and an integer a ``float`` option's float; anything else is left for the type check to answer.

    Args:
        config_class: the method's settings dataclass.
        options: the run's ``--method_options``.

    Returns:
        The options, numbers converted.
    """
    hints = typing.get_type_hints(config_class)
    out = dict(options)
    for name, value in options.items():
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        if hints.get(name) is int and isinstance(value, float) and value.is_integer():
            out[name] = int(value)
        elif hints.get(name) is float and isinstance(value, int):
            out[name] = float(value)
    return out


class ContinualMethod:
    """A continual-learning method. Class attributes declare what it is; hooks default to "do nothing".

    Attributes:
        name: the registry name (``--method``).
        substrates: ``None`` (the default): the method runs on any substrate that provides what it :attr:`requires`
            and calls the wake hooks it overrides. A set of substrate names (``Substrate.name``) restricts it to
            those, where a comparison deliberately does (the paper's SAC baselines whose memories are frozen
            critics).
        requires: the capabilities (:mod:`sr_imitation.stream.capabilities`) it asks of the substrate beyond the
            :class:`Substrate` protocol; the engine refuses a substrate without them when the run is built, and the
            method reaches them through :func:`~sr_imitation.stream.capabilities.capability`. An entry ``X | Y``
            asks for either (:func:`~sr_imitation.stream.capabilities.alternatives`).
        stores_memories: whether a frozen memory M_k is made after each wake (needed by sleep and distillation).
    """

    name: ClassVar[str] = ""
    substrates: ClassVar[frozenset[str] | None] = None
    requires: ClassVar[tuple[Any, ...]] = ()
    option_requires: ClassVar[tuple[type, ...]] = ()
    """Capabilities the method asks for only with some of its options (``--method_options``): an instance lists
    those its options need in its own ``requires``, which the engine checks (SR's expert memories and fresh wakes)."""
    stores_memories: ClassVar[bool] = False
    memory_name: ClassVar[str] = "memory"
    """The file name a method's own memory kind is saved under (``memory``: the substrate's, SR's M_k)."""
    resumable_wake_hooks: ClassVar[bool] = False
    """True when everything the wake hooks carry from one update to the next is either :class:`WakeHooks`' own
    (:attr:`WakeStep.generator`, counters) or in :meth:`wake_state` (A-GEM's reference gradient, a wake solver's warm
    start or generator); what they hold fixed is set in :meth:`begin_wake`. A mid-wake snapshot then keeps that
    state and a killed wake continues from it. False (the default, the safe answer for a method whose state is not
    declared): such a wake, killed, starts again from its start, with the same numbers."""

    own_settings: ClassVar[Mapping[str, str]] = {}
    """Shared settings the method replaces with options of its own: ``"sleep.max_iterations": "iterations"``
    (Reset & Distill's budget). ``sr-train`` refuses such a flag on the command line, in one line naming the option
    to give instead (:func:`~sr_imitation.stream.methods.registry.replaced_setting_refusal`): a setting the user
    gives is never silently replaced. The option's value is the one used and fingerprinted (``method_config.*``)."""
    fixed_settings: ClassVar[Mapping[str, Any]] = {}
    """Shared settings the method fixes, whatever the run says: ``"sleep.anchor_strength": 0.0``, or
    ``"sleep.enabled": True`` for a method that always runs its own sleep phase; refused on the command line as
    :attr:`own_settings` are."""

    def __init__(self, settings: MethodSettings) -> None:
        self.settings = settings
        self.memories: list[Memory] = []
        self.hook_calls: dict[str, int] | None = None
        """Set by the :class:`WakeHooks` of the current wake (how often each hook was called); ``None`` before."""
        if settings.options:
            self.config = with_options(self.name, getattr(type(self), "config", None), settings.options)

    def setup(self, substrate: Substrate) -> None:
        """Called once per process after ``substrate.setup()``, before any checkpoint is loaded (a method that
        changes the policy's architecture, CompoNet, does it here)."""

    # -- wake ---------------------------------------------------------------------------------------------
    def begin_wake(self, k: int, memories: Sequence[Memory], substrate: Substrate) -> None:
        """Called before the wake of stage ``k`` (also a resumed one) with the memories M_1..M_k-1 kept so far."""
        self.memories = list(memories)

    def wake_batch(self, step: WakeStep) -> Mapping[str, Tensor]:
        """The batch the update trains on, given the current skill's ``step.batch`` (CLEAR mixes in replayed
        transitions; on SAC it feeds critic and actor). Default: ``step.batch`` unchanged."""
        return step.batch

    def wake_loss(self, loss: Tensor, step: WakeStep) -> Tensor:
        """The loss the wake differentiates for this update, given the substrate's own policy loss ``loss``
        (SAC: the actor loss). Default: ``loss`` unchanged."""
        return loss

    def adjust_gradients(self, step: WakeStep) -> dict[str, float]:
        """Change ``p.grad`` of ``step.parameters`` after the backward pass, before the optimizer step; returns
        numbers to log. Default: nothing."""
        return {}

    def wake_state(self) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """What the wake hooks carry from one update to the next beyond :class:`WakeHooks`' generator and counters,
        as tensors and a JSON record; a mid-wake snapshot stores it (with :attr:`resumable_wake_hooks`). Default:
        nothing."""
        return {}, {}

    def load_wake_state(self, tensors: Mapping[str, Tensor], record: Mapping[str, Any]) -> None:
        """Restore what :meth:`wake_state` returned, after :meth:`begin_wake` of the same stage. Default: nothing."""

    WAKE_HOOKS: ClassVar[tuple[str, ...]] = WAKE_HOOKS

    @property
    def wake_state_sample(self) -> int:
        """States a SAC wake keeps from its replay at skill end for this method (EWC's Fisher samples); 0: none."""
        return 0

    @property
    def wake_transition_sample(self) -> int:
        """Transitions a SAC wake keeps from its replay at skill end for this method (CLEAR's); 0: none."""
        return 0

    @classmethod
    def wake_hooks_used(cls) -> set[str]:
        """The wake hooks this method overrides (a substrate must call every one of them)."""
        return {hook for hook in cls.WAKE_HOOKS if getattr(cls, hook) is not getattr(ContinualMethod, hook)}

    @property
    def has_wake_hooks(self) -> bool:
        """Whether :meth:`wake_batch`, :meth:`wake_loss` or :meth:`adjust_gradients` are overridden (substrates
        without hook support refuse such methods)."""
        return bool(self.wake_hooks_used())

    # -- memory -------------------------------------------------------------------------------------------
    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        """M_k, made right after wake k while the policy is theta_k^wake (only if :attr:`stores_memories`).
        Default: the substrate's memory (what SR's sleep consolidates). Must be saved with
        ``substrate.save_memory(k, memory)`` unless the substrate's :meth:`make_memory` saved it."""
        return substrate.make_memory(k)

    def save_memory(self, k: int, substrate: Substrate, memory: Memory) -> Memory:
        """Save a method's own M_k under :attr:`memory_name`, where the engine loads it back on resume
        (``substrate.load_memory(k, name=memory_name)``); returns it."""
        substrate.save_memory(k, memory, name=self.memory_name)
        return memory

    def extra_memories(self, substrate: Substrate, stages: int) -> list[Memory]:
        """Memories the method keeps besides M_1..M_K (counted in the memory budget; Progress & Compress's
        knowledge-base Fishers). Default: none."""
        return []

    def wake_memories(self, skill_number: int, memories: Sequence[Memory]) -> tuple[list[Memory], float]:
        """Memories and weight gamma_k of the wake's distillation term for the ``skill_number``-th skill
        (1-based); none by default."""
        return [], 0.0

    def sleeps_after(self, skill_number: int) -> bool:
        """Whether a sleep follows the wake of the ``skill_number``-th skill (1-based)."""
        return False

    def sleep_memories(self, k: int, memories: Sequence[Memory]) -> list[Memory]:
        """The memories the sleep after wake k consolidates (default: M_1..M_k)."""
        return list(memories[: k + 1])

    def prepare_sleep(self, k: int, problem: SleepProblem, substrate: Substrate) -> SleepProblem:
        """The sleep problem of stage k as the method wants it (default: the substrate's, i.e. SR's). A method that
        uses the sleep phase for its own offline consolidation (Reset & Distill's distillation) changes the policy
        function, the configuration or the parameters' starting point here."""
        return problem

    def own_sleep_config(self, config: Any) -> Any:
        """``config`` (the run's ``SleepConfig``) with the ``sleep.*`` entries of :attr:`fixed_settings` and
        :attr:`own_settings` (from the method's ``config``, options applied) in place of the run's values.

        Args:
            config: the sleep configuration of the substrate's :class:`SleepProblem`.

        Returns:
            A copy with the method's own values, the ones it declares.
        """
        own = {key: getattr(self.config, option) for key, option in self.own_settings.items()}
        values = {**self.fixed_settings, **own}
        names = {f.name for f in dataclasses.fields(config)}  # sleep.enabled: the run's switch, not the core's
        fields = {key.split(".", 1)[1]: value for key, value in values.items() if key.startswith("sleep.")}
        return dataclasses.replace(config, **{name: value for name, value in fields.items() if name in names})
