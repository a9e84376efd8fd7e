"""What each continual method's wake hooks cost per SAC update (docs/BENCHMARKS.md):
``python -m sr_imitation.benchmarks.wake_hooks --past=4 --repeats=200``.

One SAC update (batch 128, the 2x256 actor and twin critic of the MT5 preset, plain actor) with each method's hooks
as in wake 5 of MT5 (``--past`` memories of 1000 states of the kind the method stores, random weights and states),
against the same update without hooks; median ms over ``--repeats`` updates and the ratio to no hooks, one process,
one after another. The numbers decide how much longer a method's wake is than SR's wake-only (the environment steps,
a large share of the wake on CPU, are the same for every method and not included here).
"""

from __future__ import annotations

import argparse
import json
import platform
from typing import Any

import torch

from sr_imitation.benchmarks.timing import median_ms
from sr_imitation.core.excitability import activity_recording_off
from sr_imitation.core.memory import OutputDistillationMemory
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.stream.methods import METHODS
from sr_imitation.stream.methods.base import WakeHooks
from sr_imitation.stream.methods.clear import TransitionMemory
from sr_imitation.stream.methods.ewc import FisherMemory
from sr_imitation.stream.substrate import MethodSettings
from sr_imitation.substrates.sac.config import SACConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory
from sr_imitation.substrates.sac.sac import SACAgent


class _Substrate:
    """The capabilities the methods' wake hooks use, on one agent."""

    def __init__(self, agent: SACAgent) -> None:
        self.agent = agent

    def gaussian_policy(self, states: torch.Tensor) -> torch.Tensor:
        mean, log_std = self.agent.actor(self.agent.normalizer(states).float())
        return torch.cat([mean, log_std], dim=-1)


def _memories(method: str, agent: SACAgent, sub: _Substrate, past: int, g: torch.Generator) -> list[Any]:
    states = [torch.randn(1000, OBS_DIM, generator=g) for _ in range(past)]
    kind = {"ewc": "fisher", "der": "output", "clear": "transitions"}.get(method, "critic")
    out = []
    for i, s in enumerate(states):
        if kind == "critic":
            out.append(CriticMemory.from_agent(f"s{i}", agent, s.numpy()))
        elif kind == "output":
            out.append(OutputDistillationMemory.from_snapshot(f"s{i}", lambda o: sub.gaussian_policy(o["state"]),
                                                              {"state": s}))
        elif kind == "fisher":
            params = agent.actor_parameters()
            out.append(FisherMemory(f"s{i}", {**{f"anchor.{j:03d}": p.detach().clone() for j, p in enumerate(params)},
                                              **{f"fisher.{j:03d}": torch.rand(p.shape, generator=g)
                                                 for j, p in enumerate(params)}}))
        else:
            with torch.no_grad():
                target = sub.gaussian_policy(s)
            out.append(TransitionMemory(f"s{i}", {"obs": s, "actions": torch.rand(1000, ACT_DIM, generator=g),
                                                  "rewards": torch.rand(1000, 1, generator=g), "next_obs": s.clone(),
                                                  "terminated": torch.zeros(1000, 1), "target": target}))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--past", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--threads", type=int, default=1)
    ns = parser.parse_args()
    torch.set_num_threads(ns.threads)
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    agent = SACAgent(SACConfig(), None)
    sub = _Substrate(agent)
    batch = {"obs": torch.randn(128, OBS_DIM, generator=g), "actions": torch.rand(128, ACT_DIM, generator=g) * 2 - 1,
             "rewards": torch.rand(128, 1, generator=g), "next_obs": torch.randn(128, OBS_DIM, generator=g),
             "terminated": torch.zeros(128, 1)}
    results: dict[str, Any] = {"machine": platform.processor() or platform.machine(), "threads": ns.threads,
                               "past_memories": ns.past, "repeats": ns.repeats, "ms": {}}
    base = median_ms(lambda: agent.update(dict(batch)), ns.repeats, warmup=5)
    results["ms"]["no hooks (sr, wake_only, sequential)"] = round(base, 3)
    for name in ("ewc", "der", "agem", "clear", "nash_mtl", "pcgrad"):
        method = METHODS[name](MethodSettings(sleep=False))
        memories = _memories(name, agent, sub, ns.past, g)
        method.begin_wake(ns.past, memories, sub)
        hooks = WakeHooks(method, ns.past, agent.actor_parameters(), agent.policy_fn, seed=0,
                          quiet=lambda: activity_recording_off(agent.actor))
        ms = median_ms(lambda hooks=hooks: agent.update(dict(batch), 0.0, hooks), ns.repeats, warmup=5)
        results["ms"][name] = round(ms, 3)
    results["ratio_to_no_hooks"] = {k: round(v / base, 2) for k, v in results["ms"].items()}
    print(json.dumps(results, indent=2))  # noqa: T201


if __name__ == "__main__":
    main()
