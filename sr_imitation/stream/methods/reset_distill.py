"""Reset & Distill (Ahn et al., "Prevalence of negative transfer in continual reinforcement learning: analyses and a
simple baseline", ICLR 2025, arXiv:2403.05066; the paper's ``ahn2025reset``) as the paper's MT5 baseline (appendix
B.1), and the same recipe on the ACT imitation substrate (our port; the paper runs it on SAC only).

Each skill is learned by freshly initialized networks (SAC: actor, critic and temperature, the observation normalizer
shared; ACT: the whole policy, the stream's statistics shared), seeded from (run seed, skill), the global random
state left alone; its wake is the substrate's plain one (SAC; ACT: behaviour cloning, no distillation from earlier
memories). The trained network is frozen as that skill's expert, E_i, on stored inputs B_i of the skill:

- on a substrate with a Gaussian actor (SAC, :class:`~sr_imitation.stream.capabilities.GaussianActor`), the paper's:
  the expert's Gaussian mean and log-std on ``states`` states of the skill (paper: 1000; ours are the late-wake
  states SR's memory holds), E_i(s) = [mu_i(s), log sigma_i(s)];
- otherwise (ACT, :class:`~sr_imitation.stream.capabilities.ActorSnapshotMemory`) the substrate's own memory, which
  is exactly such a snapshot: the expert's deployed action chunks E_i(o) on ``--memory.buffer_size`` stored frames of
  the skill, SR's ACT memory kind with SR's budget (same frames per skill, same draw).

After each skill every expert so far is distilled into the shared policy pi_theta, the deployed one:

    min_theta  mean_{i <= k} E_{x ~ B_i} L_i(pi_theta(x), E_i(x))

with L_i the memory's loss: SAC, || [mu_theta(s), log sigma_theta(s)] - E_i(s) ||^2 (paper: MSE on mean and
log-std); ACT, the actor memory's distillation loss (``--policy.distill_reduction``, SR's). ``iterations`` Adam steps,
``batch_size`` inputs per expert per step, learning rate ``lr``, no anchor, no early stop. The defaults are the
paper's SAC settings (2000 steps, batch 256); on ACT the paper is silent, and our choice is the ACT presets' own sleep
budget, given as ``--method_options`` (``needle_compare``'s ``reset_distill`` variant: 1000 steps, batch 32, lr 1e-5,
SR's ``--sleep.max_iterations``, ``--sleep.batch_size`` and ``--sleep.lr`` in ``configs/needle_cpu_m16.json`` and
``configs/metaworld_mt5_imitation.json``), so that R&D and SR differ on ACT in what they do, not in the optimizer's
budget, and a run costs about what SR's does. The defaults stay the paper's, because the archived SAC runs were
fingerprinted with them.

The distillation runs in the engine's sleep phase (``sr_imitation.core.sleep_consolidate`` with the raw-gradient
mean, i.e. the gradient of the mean loss), so it is checkpointed, logged and resumed like SR's sleep. The shared
policy continues from the previous distillation; after the first skill it starts as the first expert (our choice).
``wake.eval`` measures the expert, ``sleep.eval`` the shared policy. Everything a later phase needs comes from files
(the memories, the sleep checkpoints), so a resumed run computes the same numbers.

Memory per skill: SAC, the states (1000 x 39 float32) and the expert's outputs on them (1000 x 8): 0.19 MB; ACT, the
raw frames and the expert's action chunks on them, as SR's memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from sr_imitation.core.memory import Memory
from sr_imitation.stream.capabilities import (
    ActorSnapshotMemory,
    GaussianActor,
    LikelihoodPolicy,
    ResettableNetworks,
    capability,
)
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.der import gaussian_memory, state_gaussian
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import SleepProblem, Substrate

EXPERT = "expert"
"""The file name of the Gaussian expert memories (SAC); on ACT the expert is the substrate's own memory file."""


@dataclass(frozen=True)
class ResetDistillConfig:
    iterations: int = 2000
    """Distillation steps after each skill (paper: 2000; ACT, our choice: 1000, the presets' sleep budget)."""
    batch_size: int = 256
    """Inputs per expert per step (paper: batch 256, per expert is our reading; ACT, our choice: 32, the presets'
    sleep batch)."""
    lr: float = 3e-4
    """Adam learning rate of the distillation (our choice: SAC's actor learning rate; ACT, our choice: 1e-5, the
    presets' sleep learning rate)."""


@register_method
class ResetDistill(ContinualMethod):
    """A fresh network per skill, then all experts distilled into one shared policy."""

    name = "reset_distill"
    requires: ClassVar[tuple[Any, ...]] = (ResettableNetworks, LikelihoodPolicy, GaussianActor | ActorSnapshotMemory)
    stores_memories = True
    memory_name = EXPERT
    config: ClassVar[ResetDistillConfig] = ResetDistillConfig()
    # the distillation's budget is the method's own; the flags of SR's sleep are refused, naming these options
    own_settings: ClassVar[dict[str, str]] = {"sleep.max_iterations": "iterations", "sleep.batch_size": "batch_size",
                                              "sleep.lr": "lr"}
    fixed_settings: ClassVar[dict[str, Any]] = {"sleep.aggregator": "mean_grad", "sleep.anchor_strength": 0.0,
                                                "sleep.early_stop_tol": 0.0, "sleep.enabled": True}

    def setup(self, substrate: Substrate) -> None:
        if not isinstance(substrate, GaussianActor):  # the expert is the substrate's own memory (ACT)
            self.memory_name = "memory"  # what a resume loads back

    def sleeps_after(self, skill_number: int) -> bool:
        return True  # the distillation, after every skill (not SR's sleep: --sleep.enabled is refused, fixed_settings)

    def begin_wake(self, k: int, memories: Any, substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        capability(substrate, ResettableNetworks).reset_networks(k)

    def make_memory(self, k: int, substrate: Substrate) -> Memory:
        if isinstance(substrate, GaussianActor):  # the paper's expert memory
            return self.save_memory(k, substrate, gaussian_memory(substrate, k))
        return capability(substrate, ActorSnapshotMemory).actor_memory(k)  # saved by the substrate

    def prepare_sleep(self, k: int, problem: SleepProblem, substrate: Substrate) -> SleepProblem:
        if k > 0:  # the shared policy as the previous distillation left it
            capability(substrate, ResettableNetworks).load_actor(k - 1, "sleep")
        config = self.own_sleep_config(problem.config)
        parameters = capability(substrate, LikelihoodPolicy).policy_parameters()
        # the policy as the experts' memories evaluate it: the Gaussian (SAC), the substrate's sleep policy (ACT)
        policy = state_gaussian(substrate) if isinstance(substrate, GaussianActor) else problem.policy
        return SleepProblem(parameters, policy, config)
