"""The checkpoint and file half of the :class:`~sr_imitation.stream.substrate.Substrate` protocol, written once for
every substrate (:class:`SubstrateBase`)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

from torch import Tensor, nn

from sr_imitation.core.memory import Memory, load_memory
from sr_imitation.infra.runlog import RunLog
from sr_imitation.io import CorruptFileError, load_checked_safetensors, save_checked_safetensors, write_checked_json
from sr_imitation.stream.capabilities import missing_members

SUBSTRATE_WRITES: tuple[str, ...] = (
    "name", "skills", "seed_scheme", "wake_hooks", "run_seed", "method_settings", "setup", "begin_phase", "wake",
    "make_memory", "wake_eval_skills", "evaluate", "sleep_problem", "report", "checkpoint_module", "policy_parameters")
"""The members a substrate deriving from :class:`SubstrateBase` writes itself: the protocol's policy half and the two
members of :class:`CheckpointedPolicy` (``skills`` and the output directory ``out`` are set in ``__init__``)."""


@runtime_checkable
class CheckpointedPolicy(Protocol):
    """What :class:`SubstrateBase` asks of the substrate deriving from it (checked with the protocol, by
    :func:`~sr_imitation.stream.substrate.check_substrate`)."""

    def checkpoint_module(self) -> nn.Module:
        """The module whose ``state_dict`` a checkpoint holds (the policy, or the agent with its critics)."""

    def policy_parameters(self) -> list[Tensor]:
        """theta: the deployed policy's trainable parameters, in :class:`SleepProblem.parameters` order (also
        :class:`~sr_imitation.stream.capabilities.LikelihoodPolicy`'s)."""


def load_weights(module: nn.Module, state: dict[str, Tensor], path: Path) -> None:
    """Load ``state`` into ``module``, every tensor of both: otherwise a
    :class:`~sr_imitation.io.CorruptFileError` naming ``path`` (the checkpoint) and what does not fit."""
    try:
        missing, unexpected = module.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # a shape that does not fit
        raise CorruptFileError(path, f"weights do not fit the policy: {exc}") from exc
    if missing or unexpected:
        raise CorruptFileError(path, f"weights do not match the policy (missing {missing[:5]}, "
                                     f"unexpected {unexpected[:5]})")


class SubstrateBase:
    """The checkpoint and file members of the :class:`~sr_imitation.stream.substrate.Substrate` protocol.

    A subclass sets ``self.out`` (the run directory) and ``self.skills``, declares where its files go (the layout
    attributes below: format strings with the fields ``k``, the 0-based stage, ``n`` = ``k + 1``, ``skill``,
    :meth:`memory_skill`, and for the files ``phase``, ``name`` and ``suffix``, ``""`` for the substrate's own memory
    and ``".<name>"`` for a method's), names its policy (:class:`CheckpointedPolicy`) and writes the rest of
    :data:`SUBSTRATE_WRITES`. The base then saves and loads its checkpoints (checked safetensors with a header, the
    extra files as checked JSON), its memories and the stages of a run it extends. A substrate with another checkpoint
    format (ACT's LeRobot ``pretrained_model/``) overrides :meth:`save_policy` and :meth:`checkpoint_state` only.
    """

    out: Path
    skills: list[str]
    run_log: RunLog | None = None
    """Set by the engine before the first phase."""
    extension_keys: ClassVar[tuple[str, ...]] = ("stream.skills", "stream.extend_from")
    """Settings that may differ from the finished run a run extends: the skill list and the extension setting."""

    stage_folder: ClassVar[str] = "stage{k}"
    """Stage k's folder, relative to the run directory: its checkpoints (and whatever else the substrate puts there)."""
    policy_files: ClassVar[str] = "{phase}/{name}"
    """The file ``name`` of the checkpoint after ``phase``, relative to the stage's folder."""
    checkpoint_file: ClassVar[str] = "policy.safetensors"
    """The checkpoint's weights: the file of that ``name`` among :attr:`policy_files`."""
    memory_files: ClassVar[str] = "memories/{k}{suffix}.safetensors"
    """A memory of stage k, relative to the run directory."""
    run_files: ClassVar[tuple[str, ...]] = ()
    """Files of the run directory itself that a run extending this one copies with the stages (statistics)."""

    # -- where the files are ---------------------------------------------------------------------------------
    def memory_skill(self, k: int) -> str:
        """The skill name stage ``k``'s memories carry (its name in the stream)."""
        return self.skills[k]

    def _fields(self, k: int) -> dict[str, Any]:
        return {"k": k, "n": k + 1, "skill": self.memory_skill(k)}

    def stage_dir(self, k: int) -> Path:
        """Stage ``k``'s folder (:attr:`stage_folder`)."""
        return self.out / self.stage_folder.format(**self._fields(k))

    def policy_file(self, k: int, phase: str, name: str) -> Path:
        """Where :meth:`save_policy` writes the file ``name`` of the checkpoint after ``phase`` of stage ``k``."""
        return self.stage_dir(k) / self.policy_files.format(**self._fields(k), phase=phase, name=name)

    def checkpoint_path(self, k: int, phase: str) -> Path:
        """The weights of the checkpoint after ``phase`` of stage ``k`` (:attr:`checkpoint_file`)."""
        return self.policy_file(k, phase, self.checkpoint_file)

    def memory_path(self, k: int, name: str = "memory") -> Path:
        """Where stage ``k``'s memory ``name`` is saved (:attr:`memory_files`; ``memory``: the substrate's own M_k)."""
        suffix = "" if name == "memory" else f".{name}"
        return self.out / self.memory_files.format(**self._fields(k), name=name, suffix=suffix)

    # -- memories ------------------------------------------------------------------------------------------
    def save_memory(self, k: int, memory: Memory, name: str = "memory") -> None:
        memory.save(self.memory_path(k, name))

    def load_memory(self, k: int, name: str = "memory") -> Memory:
        return load_memory(self.memory_path(k, name), skill=self.memory_skill(k))

    # -- checkpoints ---------------------------------------------------------------------------------------
    def checkpoint_header(self, k: int, phase: str) -> dict[str, Any]:
        """What a checkpoint's header holds besides its tensors (checked when it is read back)."""
        return {"stage": k, "phase": phase}

    def save_policy(self, k: int, phase: str, files: dict[str, Any]) -> None:
        """The module's state as checked safetensors (0-d tensors as shape (1,): the digest needs a dimension) and
        ``files`` as checked JSON."""
        state = {n: t.reshape(-1) if t.ndim == 0 else t for n, t in self.checkpoint_module().state_dict().items()}
        save_checked_safetensors(self.checkpoint_path(k, phase), state, self.checkpoint_header(k, phase))
        for name, obj in files.items():
            write_checked_json(self.policy_file(k, phase, name), obj)

    def checkpoint_state(self, k: int, phase: str) -> dict[str, Tensor]:
        """The state saved after ``phase`` of stage ``k``, checked (checksums, header) and in the module's shapes."""
        path = self.checkpoint_path(k, phase)
        tensors, header = load_checked_safetensors(path)
        want = self.checkpoint_header(k, phase)
        got = {key: header.get(key) for key in want}
        if got != want:
            raise CorruptFileError(path, f"checkpoint header {got} does not match the expected {want}")
        shapes = {n: t.shape for n, t in self.checkpoint_module().state_dict().items()}
        return {n: t.reshape(shapes[n]) if n in shapes and t.numel() == shapes[n].numel() else t
                for n, t in tensors.items()}

    def load_policy(self, k: int, phase: str) -> None:
        load_weights(self.checkpoint_module(), self.checkpoint_state(k, phase), self.checkpoint_path(k, phase))

    def parameter_names(self) -> list[str]:
        """The names of theta (:meth:`policy_parameters`, in its order) in the checkpoint's state."""
        names = {id(p): n for n, p in self.checkpoint_module().named_parameters()}
        return [names[id(p)] for p in self.policy_parameters()]

    def parameters_at(self, k: int, phase: str) -> list[Tensor]:
        state = self.checkpoint_state(k, phase)
        return [state[n] for n in self.parameter_names()]

    def load_actor(self, k: int, phase: str) -> None:
        """The actor of the checkpoint after ``phase`` of stage ``k``, when the checkpoint holds nothing else
        (:class:`~sr_imitation.stream.capabilities.ResettableNetworks`; a substrate with critics overrides it)."""
        self.load_policy(k, phase)

    # -- extending a finished run --------------------------------------------------------------------------
    def source_skills(self, settings: dict[str, Any]) -> list[str]:
        return list(settings["stream.skills"])

    def import_stages(self, source: Path, n: int) -> None:
        """Stages 1..n of the finished run ``source``: their folders, each stage's own memory and :attr:`run_files`
        (what lies elsewhere, such as videos, stays in the source run)."""
        for k in range(n):
            stage, memory = self.stage_dir(k).relative_to(self.out), self.memory_path(k).relative_to(self.out)
            shutil.copytree(source / stage, self.out / stage)
            if not memory.is_relative_to(stage) and (source / memory).is_file():
                (self.out / memory).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(source / memory, self.out / memory)
        for name in self.run_files:
            shutil.copy2(source / name, self.out / name)


def missing_base_members(substrate: object) -> list[str]:
    """The members of :class:`CheckpointedPolicy` that a :class:`SubstrateBase` (an instance or a class) lacks; none
    for another object."""
    kind = substrate if isinstance(substrate, type) else type(substrate)
    return missing_members(substrate, CheckpointedPolicy) if issubclass(kind, SubstrateBase) else []
