"""A toy substrate: the engine's test bed and the complete example of docs/ARCHITECTURE.md's "Adding a substrate".

A 2-layer MLP regresses a fixed random linear map per skill (torch only, milliseconds per phase). The file holds all
a substrate is: :class:`ToySubstrate` (the protocol's policy half on ``SubstrateBase``, which writes the checkpoints
and files, and a few capabilities), its run configuration (:class:`ToyConfig`), its fingerprint and stored config, and
the two functions ``sr-train`` calls (:func:`parse`, :func:`main`). A folder ``sr_imitation/substrates/toy/`` whose
``__init__.py`` registers ``module = "tests.stream.toy"`` (the recipe's code block) makes it ``--substrate=toy``.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch

from sr_imitation.core.memory import Memory, OutputDistillationMemory
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.infra.cli_errors import split_config_path
from sr_imitation.infra.cli_parsing import parse_command
from sr_imitation.infra.fingerprint import (
    RUN_DIRECTORY,
    SettingsFingerprint,
    output_dir_for,
    settings_fingerprint,
    to_jsonable,
)
from sr_imitation.io import write_checked_json
from sr_imitation.stream import MethodSettings, SleepProblem, method_class, method_config
from sr_imitation.stream.config import RunConfig, StreamSettings, StreamSleepConfig, check_shared_settings
from sr_imitation.stream.methods.base import WakeHooks
from sr_imitation.stream.run import StreamRun
from sr_imitation.stream.substrate_base import SubstrateBase


class ToySubstrate(SubstrateBase):
    """The :class:`~sr_imitation.stream.substrate.Substrate` protocol on a toy regression (module docstring)."""

    name: ClassVar[str] = "toy"
    seed_scheme: ClassVar[str] = "decimal"
    wake_hooks: ClassVar[frozenset[str]] = frozenset({"wake_batch", "wake_loss", "adjust_gradients"})
    policy_files: ClassVar[str] = "{phase}.{name}"  # stage0/wake.safetensors, stage0/wake.wake_history.json, ...
    checkpoint_file: ClassVar[str] = "safetensors"

    def __init__(self, out: Path, skills: Sequence[str], seed: int = 0, sleep: bool = True, wake_steps: int = 30,
                 sleep_iterations: int = 15, distill_weight: float = 0.5, anchor_after_final: bool = False,
                 sleep_config: SleepConfig | None = None) -> None:
        self.out, self.skills, self.seed, self.sleep = Path(out), list(skills), seed, sleep
        self.wake_steps, self.gamma = wake_steps, distill_weight
        self.sleep_config = sleep_config or SleepConfig(max_iterations=sleep_iterations, batch_size=16, lr=1e-2,
                                                        early_stop_window=5, anchor_after_final=anchor_after_final)
        self.calls: list[tuple[str, int]] = []

    @classmethod
    def from_config(cls, cfg: ToyConfig) -> ToySubstrate:
        core = {f.name: getattr(cfg.sleep, f.name) for f in dataclasses.fields(SleepConfig)}
        return cls(cfg.output_dir, cfg.stream.skills, seed=cfg.seed, sleep=cfg.sleep.enabled,
                   wake_steps=cfg.wake_steps, distill_weight=cfg.distill_weight, sleep_config=SleepConfig(**core))

    # -- what continual methods read, set-up and seeding ---------------------------------------------------------
    def method_settings(self) -> MethodSettings:
        return MethodSettings(sleep=self.sleep, distill_weight=lambda k: self.gamma)

    def setup(self) -> None:
        g = torch.Generator().manual_seed(1000 + self.seed)
        self.test_x = torch.randn(64, 4, generator=g)
        self.maps = [torch.randn(4, 2, generator=g) for _ in self.skills]  # skill k's map: the same in any stream
        torch.manual_seed(self.seed)
        self.policy = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))

    def policy_fn(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.policy(obs["x"])

    @property
    def run_seed(self) -> int:
        return self.seed

    def begin_phase(self, k: int, phase: str, seed: int) -> None:
        torch.manual_seed(seed)
        self.phase_seed = seed

    # -- the phases -----------------------------------------------------------------------------------------
    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: Any
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        self.calls.append(("wake", k))
        opt = torch.optim.SGD(self.policy.parameters(), lr=0.05)
        hooks = WakeHooks(method, k, self.policy_parameters(), self.policy_fn, self.phase_seed)
        for _ in range(self.wake_steps):
            loss = self.wake_update(k, memories, distill_weight, opt, hooks)
        return {"loss": loss.item(), **hooks.summary()}, {"wake_history.json": {"final_loss": loss.item()}}

    def wake_update(self, k: int, memories: Sequence[Memory], distill_weight: float, opt: torch.optim.Optimizer,
                    hooks: WakeHooks) -> torch.Tensor:
        """One wake update on a fresh batch of skill k, shaped by the method's hooks; returns its loss."""
        x = torch.randn(32, 4)
        batch = hooks.batch({"obs": x, "y": x @ self.maps[k]})
        loss = (self.policy(batch["obs"]) - batch["y"]).pow(2).sum(1).mean()
        for m in memories:
            loss = loss + distill_weight * m.objective(self.policy_fn, 16)
        loss = hooks.loss(loss)
        opt.zero_grad()
        loss.backward()
        hooks.adjust()
        opt.step()
        return loss

    def make_memory(self, k: int) -> Memory:
        self.calls.append(("memory", k))
        memory = OutputDistillationMemory.from_snapshot(self.skills[k], self.policy_fn, {"x": torch.randn(64, 4)})
        memory.save(self.memory_path(k))
        return memory

    def wake_eval_skills(self, k: int, sleeps: bool) -> list[int]:
        return [k] if sleeps else list(range(k + 1))

    def evaluate(self, k: int, phase: str, skills: Sequence[int]) -> dict[str, Any]:
        self.calls.append((phase, k))
        with torch.no_grad():
            err = {self.skills[i]: (self.policy(self.test_x) - self.test_x @ self.maps[i]).norm(dim=1)
                   for i in skills}
        record = {"success": {s: float((e < 1.0).float().mean()) for s, e in err.items()},
                  "error": {s: float(e.mean()) for s, e in err.items()}}
        write_checked_json(self.out / f"stage{k}" / f"{phase}.json", record)
        return record

    def sleep_problem(self, k: int, memories: Sequence[Memory]) -> SleepProblem:
        self.calls.append(("sleep", k))
        config = dataclasses.replace(self.sleep_config, seed=self.seed * 1000 + k)

        def losses() -> dict[str, Any]:
            with torch.no_grad():
                return {"memory_losses": [m.loss(self.policy_fn, dict(m.tensors)).item() for m in memories]}

        return SleepProblem(list(self.policy.parameters()), self.policy_fn, config, diagnostics=losses)

    # -- checkpoints (SubstrateBase saves and loads them), the report -------------------------------------
    def checkpoint_module(self) -> torch.nn.Module:
        return self.policy

    def report(self, progress: dict[str, Any], memories: Sequence[Memory], final_phases: Sequence[str]
               ) -> dict[str, Any]:
        final = {k: v for k, v in progress["completed"].items() if k.endswith(".eval")}
        return {"evals": {k: v["success"] for k, v in final.items()},
                "weights": self.parameters_at(len(self.skills) - 1, final_phases[-1]),  # also of a finished run
                "final_phases": list(final_phases), "memories": [m.skill for m in memories]}

    # -- capabilities beyond the protocol (sr_imitation.stream.capabilities) ---------------------------------
    def policy_parameters(self) -> list[torch.Tensor]:  # LikelihoodPolicy, SubstrateBase's theta
        return list(self.policy.parameters())

    def state_sample(self, k: int, n: int | None = None) -> torch.Tensor:  # LikelihoodPolicy
        return torch.randn(64, 4, generator=torch.Generator().manual_seed(200 + k))

    def log_likelihood(self, states: torch.Tensor, generator: torch.Generator) -> torch.Tensor:  # LikelihoodPolicy
        mean = self.policy(states)
        with torch.no_grad():
            u = mean + 0.1 * torch.randn(mean.shape, generator=generator)
        return torch.distributions.Normal(mean, 0.1).log_prob(u).sum(-1)

    def gaussian_policy(self, states: torch.Tensor) -> torch.Tensor:  # GaussianActor
        return self.policy(states)

    def memory_states(self, k: int) -> torch.Tensor:  # GaussianActor
        return torch.randn(64, 4, generator=torch.Generator().manual_seed(300 + k))

    def transition_sample(self, k: int) -> dict[str, torch.Tensor]:  # StoredTransitions
        x = torch.randn(64, 4, generator=torch.Generator().manual_seed(400 + k))
        return {"obs": x, "y": x @ self.maps[k]}

    def reset_networks(self, k: int) -> None:  # ResettableNetworks (with SubstrateBase.load_actor)
        saved = torch.random.get_rng_state()
        torch.manual_seed(500 + k)
        fresh = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
        torch.random.set_rng_state(saved)
        self.policy.load_state_dict(fresh.state_dict())


# -- the run configuration and sr-train's two functions --------------------------------------------------------
@dataclass
class ToyStreamSettings(StreamSettings):
    """``--stream.*``: the skills, each a fixed random linear map."""

    skills: list[str] = field(default_factory=lambda: ["a", "b", "c"])
    """The skills, in order."""


@dataclass
class ToySleepConfig(StreamSleepConfig):
    """``--sleep.*`` with the toy's defaults (a short sleep on small batches)."""

    max_iterations: int = 15
    batch_size: int = 16
    lr: float = 1e-2
    early_stop_window: int = 5


@dataclass
class ToyConfig(RunConfig):
    """``sr-train --substrate=toy``: the shared run settings (:class:`RunConfig`) and the toy's own."""

    substrate: str = "toy"
    """The substrate sr-train runs."""
    stream: ToyStreamSettings = field(default_factory=ToyStreamSettings)
    sleep: ToySleepConfig = field(default_factory=ToySleepConfig)
    wake_steps: int = 30
    """SGD steps per wake."""
    distill_weight: float = 0.5
    """gamma_k, the weight of the wake's distillation from the memories."""
    output_dir: Path = Path("outputs/toy")
    """Run directory."""

    def __post_init__(self) -> None:
        self.output_dir = Path(self.output_dir)
        check_shared_settings(self, ToySubstrate.name)
        method_class(self.method, ToySubstrate.name)


RESUME_ALLOW_LIST = ("output_dir", "resume", "overwrite", "progress", "wandb")
"""Settings a resume may change: where the run is and how it is watched, never what it computes."""


def fingerprint(cfg: ToyConfig) -> SettingsFingerprint:
    """What a resume must keep: every setting but :data:`RESUME_ALLOW_LIST`, and the method's (``method_config``)."""
    return settings_fingerprint(cfg, RESUME_ALLOW_LIST,
                                {"method_config": method_config(cfg.method, cfg.method_options)})


def stored_config(cfg: ToyConfig) -> dict[str, Any]:
    """``train_config.json``: the configuration less the per-invocation flags, ``output_dir`` "." (the run's own)."""
    out = {k: v for k, v in to_jsonable(cfg).items() if k not in ("resume", "overwrite")}
    out["output_dir"] = RUN_DIRECTORY
    return out


def parse(args: list[str]) -> ToyConfig:
    """The configuration a command line describes (the registered command's ``parse``)."""
    config_path, rest = split_config_path(args)
    cfg = parse_command(ToyConfig, rest, prog="sr-train", config_path=config_path)
    cfg.output_dir = output_dir_for(config_path, rest, cfg.output_dir)
    return cfg


def main(args: list[str] | None = None) -> dict[str, Any]:
    """Run or resume the stream a command line describes (the registered command's ``main``)."""
    cfg = parse(list(sys.argv[1:] if args is None else args))
    run = StreamRun(cfg, ToySubstrate.from_config(cfg), fingerprint=fingerprint(cfg), stored_config=stored_config(cfg))
    return run.run()
