"""Every continual method's wake hooks continue from a wake killed inside (``ContinualMethod.resumable_wake_hooks``):
the toy's wake writes a mid-wake snapshot through the substrates' own frame (:mod:`sr_imitation.infra.snapshot`:
the process's generators and the hooks' state, the method's :meth:`~ContinualMethod.wake_state` included) and is
killed; the resumed run ends with the weights and numbers of one never stopped. The kill is in the third wake, where
two past memories give the wake-bargaining methods three gradients (PCGrad's projection order then matters; Nash-MTL's
warm start changes its solver's iterations, not the weights here: tests/core/test_aggregators.py checks that state)
and A-GEM is between two recomputations of its reference gradient."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pytest
import torch

from sr_imitation.core.memory import Memory
from sr_imitation.infra.snapshot import load_weights, prefixed, read_snapshot, write_snapshot
from sr_imitation.stream.capabilities import missing_capabilities
from sr_imitation.stream.methods.base import WakeHooks
from sr_imitation.stream.methods.registry import METHODS
from tests.stream.conftest import KilledError, make_engine
from tests.stream.l2_anchor import L2Anchor  # registers docs/ARCHITECTURE.md's example method
from tests.stream.toy import ToySubstrate

pytestmark = pytest.mark.usefixtures("toy_methods")  # A-GEM, Nash-MTL and PCGrad on the toy too

# the package's methods with wake hooks, and the documented example (not the throwaway methods other tests register)
HOOKED = sorted(name for name, cls in METHODS.items()
                if cls.wake_hooks_used() and (cls.__module__.startswith("sr_imitation.") or cls is L2Anchor))
ON_TOY = [name for name in HOOKED if missing_capabilities(ToySubstrate, METHODS[name].requires) == []]
# not on the toy (they need stored demonstrations): replay, LwF, M2Distill, whose hooks carry only WakeHooks' own
# generator and counters (tests/substrates/act/test_wake_snapshot.py kills an ACT wake with replay's hooks)
KILL = (2, 7)  # after update 7 of the third wake (30 updates; A-GEM recomputes its reference at 0 and 30)


class SnapshottingToy(ToySubstrate):
    """The toy whose wake writes a snapshot after update ``kill_at[1]`` of stage ``kill_at[0]`` and is killed there;
    a wake that finds a snapshot continues from it (the toy's own wake, with those two steps added)."""

    kill_at: tuple[int, int] | None = None
    load_hooks: bool = True
    """False: the hooks' state is not restored (the test's check that it matters)."""

    def wake(self, k: int, memories: Sequence[Memory], distill_weight: float, method: Any
             ) -> tuple[dict[str, Any], dict[str, Any]]:
        opt = torch.optim.SGD(self.policy.parameters(), lr=0.05)  # no state: nothing to snapshot
        hooks = WakeHooks(method, k, self.policy_parameters(), self.policy_fn, self.phase_seed)
        path, identity, start = self.out / f"wake_{k}.snapshot.safetensors", {"stage": k}, 0
        if path.is_file():
            tensors, header = read_snapshot(path, identity, hooks if self.load_hooks else None)
            load_weights(path, self.policy, prefixed(tensors, "policy."), "policy")
            start = header["update"]
        for update in range(start, self.wake_steps):
            loss = self.wake_update(k, memories, distill_weight, opt, hooks)
            if self.kill_at == (k, update):
                weights = {f"policy.{n}": t for n, t in self.policy.state_dict().items()}
                write_snapshot(path, identity, weights, {"update": update + 1}, hooks if self.load_hooks else None)
                raise KilledError
        return {"loss": loss.item(), **hooks.summary()}, {"wake_history.json": {"final_loss": loss.item()}}


def _killed_and_resumed(out, name, load_hooks=True):
    engine = make_engine(out, name, substrate_class=SnapshottingToy)
    engine.substrate.kill_at, engine.substrate.load_hooks = KILL, load_hooks
    with pytest.raises(KilledError):
        engine.run()
    assert (out / f"wake_{KILL[0]}.snapshot.safetensors").is_file()
    resumed = make_engine(out, name, resume=True, substrate_class=SnapshottingToy)
    resumed.substrate.load_hooks = load_hooks
    return resumed.run()


def _same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a["weights"], b["weights"], strict=True)) and a["evals"] == b["evals"]


def test_every_method_with_wake_hooks_declares_them_resumable():
    assert len(ON_TOY) >= 6 and set(HOOKED) >= {"agem", "pcgrad", "nash_mtl", "replay", "clear", "ewc"}
    assert [name for name in HOOKED if not METHODS[name].resumable_wake_hooks] == [], \
        "declare what the hooks carry between updates (wake_state / load_wake_state) and resumable_wake_hooks"


@pytest.mark.parametrize("name", ON_TOY)
def test_a_wake_killed_inside_continues_with_every_method_s_hooks_to_the_same_results(tmp_path, name):
    reference = make_engine(tmp_path / "reference", name, substrate_class=SnapshottingToy).run()
    assert _same(_killed_and_resumed(tmp_path / "killed", name), reference)


@pytest.mark.parametrize("name", ["agem", "pcgrad", "nash_mtl", "clear"])
def test_the_hooks_state_is_what_makes_the_resumed_wake_equal(tmp_path, name):
    """Resumed without the hooks' state (their generator; A-GEM's reference, PCGrad's order generator, Nash-MTL's warm
    start), the wake continues differently: the test above can fail."""
    reference = make_engine(tmp_path / "reference", name, substrate_class=SnapshottingToy).run()
    assert not _same(_killed_and_resumed(tmp_path / "killed", name, load_hooks=False), reference)
