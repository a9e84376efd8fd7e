"""Homeostatic excitability (Eq. 3): bounds, locality, no backprop, persistence, phase rates."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from sr_imitation.core.excitability import ExcitabilityConfig, ExcitableReLU, update_excitability


def _actor() -> nn.Sequential:
    return nn.Sequential(nn.Linear(3, 8), ExcitableReLU(8), nn.Linear(8, 8), ExcitableReLU(8), nn.Linear(8, 2))


def test_forward_is_gain_times_relu():
    layer = ExcitableReLU(3)
    layer.excitability.copy_(torch.tensor([0.5, 2.0, 1.0]))
    x = torch.tensor([[1.0, -1.0, 3.0], [2.0, 4.0, -2.0]])
    torch.testing.assert_close(layer(x), torch.tensor([[0.5, 0.0, 3.0], [1.0, 8.0, 0.0]]))


def test_one_update_matches_eq_3_by_hand():
    cfg = ExcitabilityConfig(beta=0.5, target=0.1)
    layer = ExcitableReLU(2, cfg)
    layer(torch.tensor([[1.0, 0.0], [3.0, 0.0]]))  # batch-mean activity y = [2, 0]
    assert layer.homeostatic_update(rate=0.1)
    # a = 0.5 * 0.1 + 0.5 * [2, 0] = [1.05, 0.05];  e = 1 + 0.1 * (0.1 - a) = [0.905, 1.005]
    torch.testing.assert_close(layer.activity, torch.tensor([1.05, 0.05]))
    torch.testing.assert_close(layer.excitability, torch.tensor([0.905, 1.005]))
    assert not layer.homeostatic_update(rate=0.1)  # nothing recorded since: no update


@pytest.mark.parametrize("drive, bound", [(50.0, 0.1), (0.0, 5.0)])
def test_gains_stay_within_bounds(drive, bound):
    layer = ExcitableReLU(4, ExcitabilityConfig(beta=1.0))
    for _ in range(2000):
        layer(torch.full((2, 4), drive))
        layer.homeostatic_update(rate=1.0)
        assert torch.all(layer.excitability >= 0.1) and torch.all(layer.excitability <= 5.0)
    torch.testing.assert_close(layer.excitability, torch.full((4,), bound))


def test_gains_are_not_parameters_and_ignore_the_optimizer():
    actor = _actor()
    names = [n for n, _ in actor.named_parameters()]
    assert not any("excitability" in n or "activity" in n for n in names)
    layers = [m for m in actor.modules() if isinstance(m, ExcitableReLU)]
    for m in layers:
        m.excitability.fill_(1.7)
    opt = torch.optim.Adam(actor.parameters(), lr=0.1)
    loss = actor(torch.randn(16, 3)).pow(2).sum()
    loss.backward()
    opt.step()
    assert all(not m.excitability.requires_grad and torch.all(m.excitability == 1.7) for m in layers)
    assert update_excitability(actor, rate=1e-2) == 2
    assert all(not torch.all(m.excitability == 1.7) for m in layers)


def test_gains_are_saved_with_the_model():
    actor = _actor()
    actor(torch.randn(4, 3))
    update_excitability(actor, rate=0.5)
    restored = _actor()
    restored.load_state_dict(actor.state_dict())
    for a, b in zip(actor.modules(), restored.modules(), strict=True):
        if isinstance(a, ExcitableReLU):
            assert torch.equal(a.excitability, b.excitability) and torch.equal(a.activity, b.activity)


def test_phase_rates_follow_the_paper_table_and_ablations():
    cfg = ExcitabilityConfig()
    assert cfg.rate("wake", skill_index=0, episode=10) == 5e-3  # novelty, first 500 episodes of skill 1
    assert cfg.rate("wake", skill_index=0, episode=500) == 1e-3
    assert cfg.rate("wake", skill_index=3, episode=0) == 1e-3
    assert cfg.rate("sleep") == 1e-2
    assert ExcitabilityConfig(enabled=False).rate("sleep") == 0.0
    assert ExcitabilityConfig(wake_enabled=False).rate("wake", 2, 0) == 0.0
    assert ExcitabilityConfig(sleep_enabled=False).rate("sleep") == 0.0
    with pytest.raises(ValueError, match="phase"):
        cfg.rate("dream")
    with pytest.raises(ValueError, match="e_min"):
        ExcitabilityConfig(e_min=2.0)
    with pytest.raises(ValueError, match="last dimension 4"):
        ExcitableReLU(4)(torch.zeros(2, 3))
