"""CompoNet adapted to SAC, the paper's MT5 baseline (appendix B.1), written from the paper's description (Malagon
et al., ICML 2024) and the appendix's adaptation; no code of its GPL-licensed implementation was read.

Architecture (:class:`sr_imitation.substrates.sac.composed_actor.ComposedActor`, replacing the SAC actor): a shared
trunk (the
actor's 2 x 256 ReLU MLP) trained on the first skill and frozen after it; per skill j a new Gaussian head h_j (mean
and log-std from the trunk's features) and an attention over the heads 1..j, softmax(W_j phi(s) + b_j), whose logits
start at the self-bias (b_j = 2.0 on its own head, 0 elsewhere, W_j = 0: our choice of a state-dependent attention
with that initialization). The action distribution for skill j mixes the heads' means and log-stds with those
weights. In the wake of skill j only h_j and the attention j (and, for j = 1, the trunk) learn; earlier heads and
attentions stay frozen, and each module keeps the observation normalizer's statistics of the end of its wake (the
agent's normalizer moves on in later wakes; our choice, session 22: before it, frozen modules saw drifting inputs,
docs/results/mt5_compare_superseded/README.md), so earlier skills keep exactly their policies (tested: their
evaluation trajectories repeat bit for bit). A fresh twin critic per skill. Acting on
skill j uses module j: CompoNet needs the skill's identity at evaluation (the substrate selects it per evaluated
skill), unlike every other method here.

Memory: the per-skill modules (heads and attention weights) beyond a single actor; no states.

A method like the others (``--method=componet``, :func:`register_method`), in the SAC substrate's own methods folder
rather than in :mod:`sr_imitation.stream.methods` because it is SAC-specific: its composed actor subclasses SAC's
actor and is built from SAC's network settings (``SACConfig``), and it asks for ``ReplaceableActor``, which only
the SAC substrate provides. Importing :mod:`sr_imitation.substrates.sac` registers it.
"""

from __future__ import annotations

from collections.abc import Sequence

from sr_imitation.core.memory import Memory, WeightsMemory, register_memory
from sr_imitation.stream.capabilities import ReplaceableActor, capability
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.methods.registry import register_method
from sr_imitation.stream.substrate import Substrate
from sr_imitation.substrates.sac.composed_actor import ComposedActor


@register_memory
class ModuleWeights(WeightsMemory):
    """A skill's CompoNet module (head and attention weights), kept for the memory budget; no objective."""

    kind = "componet_module"
    contents = "a frozen module per skill (Gaussian head + attention weights)"


@register_method
class CompoNet(ContinualMethod):
    """A growing set of frozen per-skill modules on a frozen trunk, composed by attention."""

    name = "componet"
    requires = (ReplaceableActor,)

    def setup(self, substrate: Substrate) -> None:
        capability(substrate, ReplaceableActor).replace_actor(ComposedActor)

    @staticmethod
    def _actor(substrate: Substrate) -> ComposedActor:
        actor = capability(substrate, ReplaceableActor).current_actor()
        if not isinstance(actor, ComposedActor):
            raise TypeError(f"componet: the substrate's actor is a {type(actor).__name__}, not CompoNet's")
        return actor

    def begin_wake(self, k: int, memories: Sequence[Memory], substrate: Substrate) -> None:
        super().begin_wake(k, memories, substrate)
        self._actor(substrate).train_skill(k)
        if k > 0:
            capability(substrate, ReplaceableActor).reset_critic(k)

    def extra_memories(self, substrate: Substrate, stages: int) -> list[Memory]:
        actor = self._actor(substrate)
        skills = [substrate.memory_skill(j) for j in range(stages)]
        return [ModuleWeights(skills[j], {f"{name}.{key}": t for name, module in
                                          (("mean", actor.heads_mean[j]), ("log_std", actor.heads_log_std[j]),
                                           ("attention", actor.attention[j]))
                                          for key, t in module.state_dict().items()})
                for j in range(1, stages)]  # the first module is the plain actor every method has
