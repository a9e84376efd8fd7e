"""A toy substrate for the engine's tests (and the smallest example of implementing one): a 2-layer MLP regressing a
fixed random linear map per skill. Wake = SGD on the skill's map plus distillation from the given memories; memory =
the core's :class:`OutputDistillationMemory` on stored inputs; evaluation = fraction of test inputs within a
tolerance; checkpoints = checked safetensors. Substrate-free (torch only), a few milliseconds per phase."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import torch

from sr_imitation.core.memory import Memory, OutputDistillationMemory, load_memory
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.io import load_checked_safetensors, save_checked_safetensors, write_checked_json
from sr_imitation.stream import MethodSettings, SleepProblem
from sr_imitation.stream.methods.base import WakeStep


class ToySubstrate:
    name: ClassVar[str] = "toy"
    seed_scheme: ClassVar[str] = "decimal"
    wake_hooks: ClassVar[frozenset[str]] = frozenset({"wake_batch", "wake_loss", "adjust_gradients"})

    extension_keys: ClassVar[tuple[str, ...]] = ("skills", "extend_from")
    run_log: Any = None

    def __init__(self, out: Path, skills: Sequence[str], seed: int = 0, sleep: bool = True, wake_steps: int = 30,
                 sleep_iterations: int = 15, distill_weight: float = 0.5, anchor_after_final: bool = False) -> None:
        self.out, self.skills, self.seed, self.sleep = Path(out), list(skills), seed, sleep
        self.anchor_after_final = anchor_after_final
        self.wake_steps, self.sleep_iterations, self.gamma = wake_steps, sleep_iterations, distill_weight
        self.calls: list[tuple[str, int]] = []

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

    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: Any = None
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        self.calls.append(("wake", k))
        opt = torch.optim.SGD(self.policy.parameters(), lr=0.05)
        hooks = method is not None and method.has_wake_hooks
        generator = torch.Generator().manual_seed(100 + k)
        for update in range(self.wake_steps):
            x = torch.randn(32, 4)
            step = WakeStep(k, update, self.policy_parameters(), self.policy_fn, {"obs": x, "y": x @ self.maps[k]},
                            generator)
            if hooks:
                step.batch = method.wake_batch(step)
            loss = (self.policy(step.batch["obs"]) - step.batch["y"]).pow(2).sum(1).mean()
            for m in memories:
                loss = loss + distill_weight * m.objective(self.policy_fn, 16)
            if hooks:
                loss = method.wake_loss(loss, step)
            opt.zero_grad()
            loss.backward()
            if hooks:
                method.adjust_gradients(step)
            opt.step()
        return {"loss": loss.item()}, {"wake_history.json": {"final_loss": loss.item()}}

    def make_memory(self, k: int) -> Memory:
        self.calls.append(("memory", k))
        memory = OutputDistillationMemory.from_snapshot(self.skills[k], self.policy_fn, {"x": torch.randn(64, 4)})
        memory.save(self.out / "memories" / f"{k}.safetensors")
        return memory

    def save_memory(self, k: int, memory: Memory, name: str = "memory") -> None:
        memory.save(self.out / "memories" / f"{k}.{name}.safetensors")

    def load_memory(self, k: int, name: str = "memory") -> Memory:
        path = self.out / "memories" / (f"{k}.safetensors" if name == "memory" else f"{k}.{name}.safetensors")
        return load_memory(path, skill=self.skills[k])

    # what continual methods ask of the policy (the SAC substrate's names)
    def policy_parameters(self) -> list[torch.Tensor]:
        return list(self.policy.parameters())

    def state_sample(self, k: int, n: int | None = None) -> torch.Tensor:
        return torch.randn(64, 4, generator=torch.Generator().manual_seed(200 + k))

    def reset_networks(self, k: int) -> None:
        saved = torch.random.get_rng_state()
        torch.manual_seed(500 + k)
        fresh = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
        torch.random.set_rng_state(saved)
        self.policy.load_state_dict(fresh.state_dict())

    def load_actor(self, k: int, phase: str) -> None:
        self.load_policy(k, phase)

    def memory_skill(self, k: int) -> str:
        return self.skills[k]

    def gaussian_policy(self, states: torch.Tensor) -> torch.Tensor:
        return self.policy(states)

    def log_likelihood(self, states: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        mean = self.policy(states)
        with torch.no_grad():
            u = mean + 0.1 * torch.randn(mean.shape, generator=generator)
        return torch.distributions.Normal(mean, 0.1).log_prob(u).sum(-1)

    def transition_sample(self, k: int) -> dict[str, torch.Tensor]:
        x = torch.randn(64, 4, generator=torch.Generator().manual_seed(400 + k))
        return {"obs": x, "y": x @ self.maps[k]}

    def memory_states(self, k: int) -> torch.Tensor:
        return torch.randn(64, 4, generator=torch.Generator().manual_seed(300 + k))

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
        config = SleepConfig(max_iterations=self.sleep_iterations, batch_size=16, lr=1e-2, early_stop_window=5,
                             seed=self.seed * 1000 + k, anchor_after_final=self.anchor_after_final)
        def losses() -> dict[str, Any]:
            with torch.no_grad():
                return {"memory_losses": [m.loss(self.policy_fn, dict(m.tensors)).item() for m in memories]}

        return SleepProblem(list(self.policy.parameters()), self.policy_fn, config, diagnostics=losses)

    def _path(self, k: int, phase: str) -> Path:
        return self.out / f"stage{k}" / f"{phase}.safetensors"

    def save_policy(self, k: int, phase: str, files: dict[str, Any]) -> None:
        save_checked_safetensors(self._path(k, phase), dict(self.policy.state_dict()), {"stage": k, "phase": phase})
        for name, obj in files.items():
            write_checked_json(self.out / f"stage{k}" / f"{phase}.{name}", obj)

    def load_policy(self, k: int, phase: str) -> None:
        tensors, _ = load_checked_safetensors(self._path(k, phase))
        self.policy.load_state_dict(tensors)

    def parameters_at(self, k: int, phase: str) -> list[torch.Tensor]:
        tensors, _ = load_checked_safetensors(self._path(k, phase))
        return [tensors[n] for n, _ in self.policy.named_parameters()]

    def source_skills(self, settings: dict[str, Any]) -> list[str]:
        return list(settings["skills"])

    def import_stages(self, source: Path, n: int) -> None:
        import shutil

        for k in range(n):
            shutil.copytree(source / f"stage{k}", self.out / f"stage{k}")
            (self.out / "memories").mkdir(exist_ok=True)
            if (source / "memories" / f"{k}.safetensors").exists():
                shutil.copy2(source / "memories" / f"{k}.safetensors", self.out / "memories" / f"{k}.safetensors")

    def report(self, progress: dict[str, Any], memories: Sequence[Memory], final_phases: Sequence[str]
               ) -> dict[str, Any]:
        final = {k: v for k, v in progress["completed"].items() if k.endswith(".eval")}
        return {"evals": {k: v["success"] for k, v in final.items()},
                "weights": [p.detach().clone() for p in self.policy.parameters()],
                "final_phases": list(final_phases), "memories": [m.skill for m in memories]}
