"""What a substrate (a policy family with its data, environment and files) provides to the stream engine.

The engine (:mod:`sr_imitation.stream.engine`) runs Algorithm 1 and owns the order of the phases and resume; the one
call of :func:`~sr_imitation.core.sleep.sleep_consolidate` is :meth:`SleepProblem.consolidate` (the engine's sleep
and ``sr-sleep`` both go through it). A substrate owns everything that depends on the
policy: how a wake trains, what a memory holds, how the policy is evaluated, seeded and saved. Two implement it:
the ACT imitation substrate (:class:`sr_imitation.substrates.act.substrate.ACTSubstrate`) and the SAC substrate, both
on :class:`~sr_imitation.stream.substrate_base.SubstrateBase` (the checkpoint and file half, written once).

Phases are named ``wake``, ``memory``, ``wake.eval``, ``sleep`` and ``sleep.eval``; ``k`` is the 0-based stage
index (skill ``skills[k]``).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from torch import Tensor

from sr_imitation.core.memory import Memory
from sr_imitation.core.sleep import SleepConfig, SleepResult, sleep_consolidate
from sr_imitation.infra.runlog import RunLog
from sr_imitation.stream.capabilities import missing_members
from sr_imitation.stream.substrate_base import missing_base_members

PHASES: tuple[str, ...] = ("wake", "memory", "wake.eval", "sleep", "sleep.eval")
"""Every phase of a stage, in the engine's order (a stage without sleep has the first three)."""
PHASE_IDS: dict[str, int] = {phase: i for i, phase in enumerate(PHASES)}
"""Each phase's number (wake 0 ... sleep.eval 4): what a phase's seed is derived from, with the run seed and the
stage (:func:`phase_seed`)."""


def seed_sequence(seed: int, stage: int, salt: int = 0) -> int:
    """numpy's ``SeedSequence([seed, stage, salt])``'s first word: a per-stage seed independent of whether earlier
    stages ran in this process (the SAC substrate's generators within a phase use their own salts)."""
    return int(np.random.SeedSequence([seed, stage, salt]).generate_state(1)[0])


SEED_SCHEMES: dict[str, Callable[[int, int, str], int]] = {
    # seed * 1000 + 10 * stage + phase id (stage 1-based): the ACT substrate's (and the toy's) since its first runs
    "decimal": lambda seed, k, phase: seed * 1000 + 10 * (k + 1) + PHASE_IDS[phase],
    # SeedSequence([seed, k, 0]) for the wake, salt 10 + phase id for the others: the SAC substrate's
    "seed_sequence": lambda seed, k, phase: seed_sequence(seed, k, 0 if phase == "wake" else 10 + PHASE_IDS[phase]),
}
"""How a phase's seed follows from the run seed, the stage (0-based) and the phase, by name. Two schemes, because the
two substrates' archived results were produced with them and must stay reproducible bit for bit; a new substrate
picks one (our choice: either; they differ only in how the numbers are spread)."""


WAKE_HOOKS: tuple[str, ...] = ("wake_batch", "wake_loss", "adjust_gradients")
"""The hooks a continual method may override in a substrate's wake loop (:attr:`Substrate.wake_hooks` names those
its wake calls)."""


def phase_seed(scheme: str, seed: int, k: int, phase: str) -> int:
    """The seed the engine hands phase ``phase`` of stage ``k`` (0-based) of a run with training seed ``seed``
    (:data:`SEED_SCHEMES`); e.g. the ``--sleep.seed`` with which ``sr-sleep`` repeats a run's sleep."""
    return SEED_SCHEMES[scheme](seed, k, phase)


@dataclass
class SleepProblem:
    """What the core's sleep needs from the substrate at stage k (besides memories, anchor and gate snapshots,
    which the engine supplies).

    Attributes:
        parameters: theta, the deployed policy's trainable parameters (updated in place).
        policy: what the memories evaluate (:meth:`Memory.loss`'s ``policy`` argument).
        config: the sleep hyperparameters, seeded for this stage.
        step_callback: called after every sleep update (e.g. the SAC actor's sleep-rate excitability, Eq. 3).
        diagnostics: called before and after the sleep; its values are recorded as ``<key>_before`` /
            ``<key>_after`` in the sleep record (e.g. each frozen critic's value of the actor).
        regularizer: an extra term R(theta) added to the sleep objective outside the bargaining (a method's,
            e.g. Progress & Compress's EWC penalty; none for SR).
    """

    parameters: Sequence[Tensor]
    policy: Any
    config: SleepConfig
    step_callback: Callable[[int], None] | None = None
    diagnostics: Callable[[], dict[str, Any]] | None = None
    regularizer: Callable[[Sequence[Tensor]], Tensor] | None = None

    def consolidate(self, memories: Sequence[Memory], anchor: Sequence[Tensor] | None,
                    wake_snapshots: Sequence[Sequence[Tensor]], is_final_skill: bool, progress: bool = True,
                    on_iteration: Callable[[int, dict[str, Any]], None] | None = None) -> SleepResult:
        """Algorithm 1, lines 7-15 on this problem: the core's sleep over ``memories`` with the anchor theta_{k-1}^sleep
        (``None``: none), the gate snapshots theta_i^wake (i < k) and this problem's step callback and regularizer.
        The stream engine's sleep and ``sr-sleep`` both sleep through it, so the anchor's rule
        (:func:`~sr_imitation.core.sleep.anchor_coefficient`) is decided in one place for both."""
        return sleep_consolidate(self.parameters, self.policy, memories, self.config, anchor_params=anchor,
                                 wake_snapshots=wake_snapshots, is_final_skill=is_final_skill,
                                 step_callback=self.step_callback, progress=progress, on_iteration=on_iteration,
                                 regularizer=self.regularizer)


@dataclass
class MethodSettings:
    """What a substrate tells a continual method about its configuration (substrate-free).

    Attributes:
        sleep: whether sleeping is enabled by the run's configuration (``--sleep.enabled`` on every substrate);
            a method that sleeps honours it.
        distill_weight: gamma_k, the weight of wake-time distillation from the memories for the k-th skill
            (1-based); ``None`` when the substrate's wake has no distillation term (SAC).
        extra: substrate-specific settings a method may read.
        options: ``--method_options``: values for fields of the method's own ``config`` (e.g. EWC's ``lam``), set
            by :func:`~sr_imitation.stream.methods.make_method` from the run's configuration (a substrate leaves it
            empty).
    """

    sleep: bool = True
    distill_weight: Callable[[int], float] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Substrate(Protocol):
    """The policy-specific half of a stream run (see the module docstring)."""

    name: ClassVar[str]
    """The substrate's name (``act``, ``sac``): ``--substrate``, and what a method restricted to some substrates
    names in :attr:`ContinualMethod.substrates`."""

    skills: list[str]

    run_log: RunLog | None
    """Set by the engine before the first phase: the run's :class:`~sr_imitation.infra.runlog.RunLog`, where the
    substrate logs what happens inside a phase (wake epochs); ``None`` until then."""

    def memory_skill(self, k: int) -> str:
        """The skill name the memories of stage ``k`` carry."""

    def method_settings(self) -> MethodSettings:
        """The settings continual methods read (sleep on/off, distillation weights)."""

    def setup(self) -> None:
        """Build the policy, its statistics and environments (after the run directory is prepared)."""

    seed_scheme: ClassVar[str]
    """How the engine derives each phase's seed from the run seed (a key of :data:`SEED_SCHEMES`)."""

    @property
    def run_seed(self) -> int:
        """The run's training seed (``--seed``)."""

    def begin_phase(self, k: int, phase: str, seed: int) -> None:
        """Seed every random generator for ``phase`` of stage ``k`` from ``seed``, the seed the engine hands the
        phase (:func:`phase_seed`: from the run seed, stage and phase only, so a resumed run continues with the same
        numbers)."""

    wake_hooks: ClassVar[frozenset[str]]
    """Which of the method's wake hooks (``wake_batch``, ``wake_loss``, ``adjust_gradients``) :meth:`wake` calls at
    every policy update (with a ``sr_imitation.stream.methods.WakeStep``); a method overriding another one is
    refused."""

    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: Any
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Train the policy on skill ``k`` (with distillation from ``memories`` at ``distill_weight`` where the
        substrate supports it, and ``method``'s wake hooks where :attr:`wake_hooks`). Returns the progress record
        and extra JSON files for the wake checkpoint."""

    def make_memory(self, k: int) -> Memory:
        """M_k from the policy right after its wake, saved to the run directory."""

    def save_memory(self, k: int, memory: Memory, name: str = "memory") -> None:
        """Save a method's own memory M_k (e.g. EWC's snapshot and Fisher) where :meth:`load_memory` finds it."""

    def load_memory(self, k: int, name: str = "memory") -> Memory:
        """M_k as it was saved under ``name`` (any registered memory kind; checked)."""

    def wake_eval_skills(self, k: int, sleeps: bool) -> list[int]:
        """Which learned skills the evaluation right after wake k covers (all learned skills when no sleep follows,
        since it is then the stage's evaluation)."""

    def evaluate(self, k: int, phase: str, skills: Sequence[int]) -> dict[str, Any]:
        """Evaluate the current policy on ``skills`` (indices), write the phase's evaluation files, return the
        progress record."""

    def sleep_problem(self, k: int, memories: Sequence[Memory]) -> SleepProblem:
        """The parameters, policy function, seeded config and callbacks of the sleep at stage ``k``."""

    def save_policy(self, k: int, phase: str, files: dict[str, Any]) -> None:
        """Checkpoint the policy after ``phase`` (``wake`` or ``sleep``) of stage ``k`` with extra JSON files."""

    def policy_file(self, k: int, phase: str, name: str) -> Path:
        """Where :meth:`save_policy` writes the extra file ``name`` of the checkpoint after ``phase`` of stage ``k``
        (the engine checks that every file it handed over is there: a substrate cannot drop one silently)."""

    def load_policy(self, k: int, phase: str) -> None:
        """Restore the policy saved by :meth:`save_policy` (checked)."""

    def parameters_at(self, k: int, phase: str) -> list[Tensor]:
        """The trainable parameters (in :class:`SleepProblem.parameters` order) saved after ``phase`` of stage k."""

    extension_keys: ClassVar[tuple[str, ...]]
    """Settings that may differ between a run and the finished run it extends (``extend_from``): the skill list
    and the extension setting itself (fnmatch patterns over the fingerprint's dotted keys)."""

    def source_skills(self, settings: dict[str, Any]) -> list[str]:
        """The skills of a finished run, from its stored (flat) settings."""

    def import_stages(self, source: Path, n: int) -> None:
        """Copy stages 1..n of the finished run ``source`` (checkpoints, memories, evaluation files) into this run."""

    def report(self, progress: dict[str, Any], memories: Sequence[Memory], final_phases: Sequence[str]
               ) -> dict[str, Any]:
        """Build results, tables and plots from the recorded phases; ``final_phases[k]`` is the phase whose
        checkpoint ends stage k (``sleep`` or ``wake``)."""


class SubstrateProtocolError(TypeError, ValueError):
    """A substrate that does not keep the :class:`Substrate` protocol, named in one line with every problem found (a
    user error on the command line: :mod:`sr_imitation.infra.cli_errors` prints it without a traceback)."""


DECLARED_TYPES: dict[str, tuple[type, ...]] = {"name": (str,), "seed_scheme": (str,), "wake_hooks": (set, frozenset),
                                               "extension_keys": (tuple, list), "skills": (list, tuple)}
"""The protocol's data members and the types their values must have."""


def _protocol_problems(substrate: object) -> list[str]:
    """Everything wrong with ``substrate``'s members besides missing ones: a data member of another type, a method
    that is not callable or cannot take the protocol's arguments, an unknown seed scheme or wake hook."""
    kind, problems = type(substrate).__name__, []
    for name, types in DECLARED_TYPES.items():
        value = inspect.getattr_static(substrate, name)
        if not isinstance(value, types):
            problems.append(f"{kind}.{name} must be a {' or '.join(t.__name__ for t in types)}, got "
                            f"{type(value).__name__}")
        elif name in ("wake_hooks", "extension_keys", "skills") and not all(isinstance(v, str) for v in value):
            problems.append(f"{kind}.{name} must hold names (str)")
    for name, member in vars(Substrate).items():
        if name.startswith("_") or not inspect.isfunction(member):
            continue
        impl = getattr(substrate, name)  # bound on an instance; on a class, the function with its self
        if not callable(impl):
            problems.append(f"{kind}.{name} is not callable")
            continue
        wanted = [p for p in inspect.signature(member).parameters if p != "self"]
        unbound = isinstance(substrate, type) and inspect.isfunction(impl)
        try:
            inspect.signature(impl).bind(*([None] * (len(wanted) + unbound)))
        except TypeError:
            problems.append(f"{kind}.{name} does not take the protocol's arguments ({', '.join(wanted)})")
        except ValueError:  # no signature (a builtin): nothing to check
            pass
    scheme = inspect.getattr_static(substrate, "seed_scheme")
    if isinstance(scheme, str) and scheme not in SEED_SCHEMES:
        problems.append(f"{kind}.seed_scheme: unknown scheme {substrate.seed_scheme!r}; "  # type: ignore[attr-defined]
                        f"choose from {sorted(SEED_SCHEMES)}")
    hooks = inspect.getattr_static(substrate, "wake_hooks")
    if isinstance(hooks, (set, frozenset)) and (unknown := sorted(set(hooks) - set(WAKE_HOOKS))):
        problems.append(f"{kind}.wake_hooks: unknown hooks {unknown}; choose from {list(WAKE_HOOKS)}")
    return problems


def check_substrate(substrate: object) -> None:
    """Refuse, in one line and before anything is written, an object that is not a :class:`Substrate`: every
    protocol member it lacks is named, then every member of the wrong kind (:data:`DECLARED_TYPES`, a method that is
    not callable or does not take the protocol's arguments), a ``seed_scheme`` outside :data:`SEED_SCHEMES` and
    ``wake_hooks`` outside :data:`WAKE_HOOKS`. A :class:`~sr_imitation.stream.substrate_base.SubstrateBase` lacking a
    member of :class:`~sr_imitation.stream.substrate_base.CheckpointedPolicy` has it named with the others. Raises
    :class:`SubstrateProtocolError`."""
    kind = type(substrate).__name__
    missing = sorted(missing_members(substrate, Substrate) + missing_base_members(substrate))
    if missing:
        raise SubstrateProtocolError(f"{kind} is not a Substrate (sr_imitation.stream.substrate): it lacks "
                                     f"{', '.join(missing)}")
    problems = _protocol_problems(substrate)
    if problems:
        raise SubstrateProtocolError("; ".join(problems))


def check_hook_calls(substrate: object, method: Any) -> None:
    """After a wake: every wake hook the substrate declares (:attr:`Substrate.wake_hooks`) and the method overrides
    was called as often as the others, through a :class:`~sr_imitation.stream.methods.WakeHooks`; otherwise a
    :class:`SubstrateProtocolError` naming them (a hook left out would change nothing, silently). A wake that made no
    update (resumed at its end) passes."""
    used = sorted(set(method.wake_hooks_used()) & set(getattr(substrate, "wake_hooks", ())))
    if not used:
        return
    kind = type(substrate).__name__
    calls = method.hook_calls
    if calls is None:
        raise SubstrateProtocolError(f"{kind}.wake did not hand {method.name!r} its wake hooks (no WakeHooks was made; "
                                     f"it declares {used} in wake_hooks)")
    declared = getattr(substrate, "wake_hooks", ())
    counts = {hook: calls.get(hook, 0) for hook in WAKE_HOOKS if hook in declared}
    if len(set(counts.values())) > 1:
        raise SubstrateProtocolError(f"{kind}.wake called the wake hooks {counts} times: a substrate calls every hook "
                                     "it declares in wake_hooks once per policy update (WakeHooks.batch, .loss, "
                                     ".adjust)")
