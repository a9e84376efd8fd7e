"""Sleep consolidation (Algorithm 1 lines 7-15) on a toy two-skill problem with conflicting memories."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from sr_imitation.core.memory import OutputDistillationMemory
from sr_imitation.core.sleep import (
    NonFiniteSleepError,
    SleepConfig,
    anchor_coefficient,
    anchor_gate_decides,
    cosine_matrix,
    parameter_distance,
    sleep_consolidate,
)


def _net() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(2, 16), nn.Tanh(), nn.Linear(16, 2))


def _skill_data(center: float, sign: float, n: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(int(10 * center) + 7)
    x = center + 0.6 * (torch.rand(n, 2, generator=g) - 0.5) * 2  # overlapping input regions
    y = torch.stack([sign * torch.sin(2 * x[:, 0]), sign * x[:, 1]], dim=1)
    return x, y


def _wake(net: nn.Module, x: torch.Tensor, y: torch.Tensor, steps: int = 400) -> None:
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(steps):
        opt.zero_grad()
        nn.functional.mse_loss(net(x), y).backward()
        opt.step()


def _policy(net: nn.Module):
    return lambda obs: net(obs["x"])


@pytest.fixture(scope="module")
def stream():
    """Two skills learned sequentially (wake only): the second overwrites the first where inputs overlap."""
    net = _net()
    xa, ya = _skill_data(-0.3, +1.0)
    xb, yb = _skill_data(+0.3, -1.0)
    _wake(net, xa, ya)
    theta_a = [p.detach().clone() for p in net.parameters()]
    mem_a = OutputDistillationMemory.from_snapshot("a", _policy(net), {"x": xa})
    _wake(net, xb, yb)
    theta_b = [p.detach().clone() for p in net.parameters()]
    mem_b = OutputDistillationMemory.from_snapshot("b", _policy(net), {"x": xb})
    return net, theta_a, theta_b, [mem_a, mem_b]


def _worst_loss(net: nn.Module, memories) -> float:
    with torch.no_grad():
        return max(
            float(m.loss(_policy(net), dict(m.tensors.items()))) for m in memories
        )


def _config(**kw) -> SleepConfig:
    base = {"lr": 5e-3, "max_iterations": 300, "batch_size": 64, "anchor_tau": None, "early_stop_window": 50,
                "early_stop_tol": 0.0, "seed": 0}
    base.update(kw)
    return SleepConfig(**base)


def test_sleep_lowers_the_worst_memory_loss_compared_with_no_sleep(stream):
    net0, _, theta_b, memories = stream
    net = copy.deepcopy(net0)
    before = _worst_loss(net, memories)
    fingerprints = [m.fingerprint() for m in memories]
    result = sleep_consolidate(list(net.parameters()), _policy(net), memories, _config(), progress=False)
    after = _worst_loss(net, memories)
    assert before > 0.05  # wake-only forgot skill a
    assert after < 0.5 * before
    assert [m.fingerprint() for m in memories] == fingerprints  # memories stay frozen
    assert result.stop_iteration == 300 and result.stop_reason == "max_iterations"
    assert len(result.alpha) == 300 and all(abs(sum(a) - 1) < 1e-9 for a in result.alpha)
    assert len(result.grad_norms[0]) == 2 and len(result.memory_losses[0]) == 2


class _LoudMemory(OutputDistillationMemory):
    """A memory whose loss (and gradient) is ``scale`` times larger, e.g. actions in other units."""

    scale = 1.0

    def loss(self, policy, batch):
        return super().loss(policy, batch) * type(self).scale


def _unscaled_losses(net: nn.Module, memories) -> list[float]:
    with torch.no_grad():
        return [float(OutputDistillationMemory.loss(m, _policy(net), dict(m.tensors.items()))) for m in memories]


def test_nash_ignores_gradient_scale_and_mean_grad_lets_the_loud_memory_dominate(stream, monkeypatch):
    """Section 3's motivation for Nash: the raw-gradient mean is "sensitive to gradient scale".

    Three memories, all with a positive loss at the start; memory c's loss is multiplied by 1 or 100. Nash
    bargains over unit directions, so its sleep is the same at both scales; the raw mean follows c at scale 100:
    c's loss vanishes while skill b is forgotten (worse than before sleep), where Nash lowers the worst loss.
    """
    net0, _, _, memories = stream
    xc, yc = _skill_data(0.0, 0.5)
    net_c = copy.deepcopy(net0)
    _wake(net_c, xc, yc, steps=200)
    mem_c = _LoudMemory.from_snapshot("c", _policy(net_c), {"x": xc})
    start = copy.deepcopy(net_c)
    _wake(start, *_skill_data(0.15, -0.3), steps=100)  # a fourth skill: every memory starts with a loss
    mems = [*memories, mem_c]
    before = _unscaled_losses(start, mems)
    assert min(before) > 0.1
    finals, losses, alphas = {}, {}, {}
    for scale in (1.0, 100.0):
        monkeypatch.setattr(_LoudMemory, "scale", scale)
        for name in ("nash", "mean_grad"):
            net = copy.deepcopy(start)
            result = sleep_consolidate(list(net.parameters()), _policy(net), mems,
                                       _config(aggregator=name, max_iterations=200), progress=False)
            assert result.stop_iteration == 200 and len(result.alpha) == 200
            assert all(len(a) == 3 and abs(sum(a) - 1) < 1e-9 and min(a) >= 0 for a in result.alpha)
            finals[name, scale] = [p.detach().clone() for p in net.parameters()]
            losses[name, scale] = _unscaled_losses(net, mems)
            alphas[name, scale] = result.alpha
    moved = parameter_distance(finals["nash", 1.0], list(start.parameters()))
    # Nash: the same sleep at both scales (only eps = 1e-5 in g/(||g|| + eps) differs) ...
    assert parameter_distance(finals["nash", 1.0], finals["nash", 100.0]) < 1e-2 * moved
    torch.testing.assert_close(torch.tensor(alphas["nash", 1.0]), torch.tensor(alphas["nash", 100.0]),
                               atol=1e-3, rtol=0)
    # ... and not the uniform mean: the memories conflict unequally, so Nash weighs them unequally.
    assert max(abs(a - 1 / 3) for a in alphas["nash", 1.0][0]) > 0.1
    assert all(a == [1 / 3] * 3 for a in alphas["mean_grad", 100.0])
    # The raw mean moves somewhere else when one memory gets louder ...
    assert parameter_distance(finals["mean_grad", 1.0], finals["mean_grad", 100.0]) > 0.3 * moved
    # ... the loud memory dominates: its loss vanishes and another memory ends worse than before sleep.
    loud = losses["mean_grad", 100.0]
    assert loud[2] < 0.01 * before[2]
    assert max(loud[:2]) > max(before)
    # Nash lowers the worst memory loss whatever the scale, far below the raw mean's.
    for scale in (1.0, 100.0):
        assert max(losses["nash", scale]) < 0.5 * max(before)
    assert max(losses["nash", 100.0]) < 0.5 * max(loud)


def test_anchor_pulls_toward_the_previous_checkpoint(stream):
    net0, theta_a, theta_b, memories = stream
    distances = {}
    for lam in (0.0, 5.0):
        net = copy.deepcopy(net0)
        result = sleep_consolidate(
            list(net.parameters()), _policy(net), memories, _config(anchor_strength=lam, max_iterations=150),
            anchor_params=theta_a, wake_snapshots=[theta_a], progress=False,
        )
        assert result.anchor_lambda == lam
        distances[lam] = parameter_distance(list(net.parameters()), theta_a)
    start = parameter_distance(theta_b, theta_a)
    assert distances[5.0] < distances[0.0]
    assert distances[5.0] < start


def test_anchor_gate_of_eq_2():
    params = [torch.zeros(3)]
    near, far = [torch.full((3,), 1.0)], [torch.full((3,), 100.0)]  # distances sqrt(3) and 100 sqrt(3)
    lam, dist = anchor_coefficient(params, [far, near], strength=0.01, tau=2.0)
    assert lam == 0.01 and dist == pytest.approx([100 * 3**0.5, 3**0.5])
    assert anchor_coefficient(params, [far], strength=0.01, tau=2.0)[0] == 0.0
    assert anchor_coefficient(params, [far], strength=0.01, tau=None)[0] == 0.01
    assert anchor_coefficient(params, [near], 0.01, 2.0, is_final_skill=True)[0] == 0.0
    assert anchor_coefficient(params, [near], 0.01, 2.0, is_final_skill=True, apply_after_final=True)[0] == 0.01
    # The gate flips exactly at tau.
    assert anchor_coefficient(params, [near], 0.01, tau=3**0.5 + 1e-9)[0] == 0.01
    assert anchor_coefficient(params, [near], 0.01, tau=3**0.5 - 1e-9)[0] == 0.0


@pytest.mark.parametrize("strength", [0.0, 0.01])
@pytest.mark.parametrize("tau", [None, 2.0])
@pytest.mark.parametrize("final", [False, True])
@pytest.mark.parametrize("after_final", [False, True])
def test_the_gate_needs_its_snapshots_exactly_when_it_can_change_the_anchor(strength, tau, final, after_final):
    """sr-sleep asks anchor_gate_decides whether the wake snapshots are required; the answer must be yes exactly when
    the snapshots change the coefficient the sleep uses (one rule for the engine and sr-sleep, issue 61 item 4)."""
    config = SleepConfig(anchor_strength=strength, anchor_tau=tau, anchor_after_final=after_final)
    params, near, far = [torch.zeros(3)], [torch.full((3,), 1.0)], [torch.full((3,), 100.0)]
    coefficients = {anchor_coefficient(params, snaps, strength, tau, final, after_final)[0]
                    for snaps in ([near], [far], [])}
    assert anchor_gate_decides(config, final) == (len(coefficients) > 1)


class _NaNMemory(OutputDistillationMemory):
    def loss(self, policy, batch):
        return super().loss(policy, batch) * float("nan")


def test_non_finite_gradients_never_update_the_policy(stream):
    net0, _, _, memories = stream
    net = copy.deepcopy(net0)
    bad = _NaNMemory("broken", dict(memories[0].tensors))
    before = [p.detach().clone() for p in net.parameters()]
    with pytest.raises(NonFiniteSleepError, match="broken"):
        sleep_consolidate(list(net.parameters()), _policy(net), [memories[1], bad],
                          _config(max_nonfinite_steps=3), progress=False)
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))


def test_early_stopping_on_a_plateau(stream):
    net0, _, _, memories = stream
    net = copy.deepcopy(net0)
    result = sleep_consolidate(list(net.parameters()), _policy(net), memories,
                               _config(lr=1e-9, max_iterations=1000, early_stop_window=20, early_stop_tol=1e-2),
                               progress=False)
    # Window means differ only by batch-sampling noise: stops at a window boundary long before the budget.
    assert result.stop_reason == "plateau"
    assert result.stop_iteration % 20 == 0 and 40 <= result.stop_iteration < 1000


def test_same_seed_same_result_and_callback_runs_each_step(stream):
    net0, _, _, memories = stream
    finals, calls = [], []
    for _ in range(2):
        net = copy.deepcopy(net0)
        sleep_consolidate(list(net.parameters()), _policy(net), memories, _config(max_iterations=30),
                          step_callback=calls.append, progress=False)
        finals.append([p.detach().clone() for p in net.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*finals, strict=True))
    assert calls == list(range(30)) * 2


def test_invalid_configs_are_rejected():
    with pytest.raises(ValueError, match=r"sleep.lr must be > 0, got 0"):
        SleepConfig(lr=0)
    with pytest.raises(ValueError, match="unknown aggregator"):
        SleepConfig(aggregator="sum")
    assert SleepConfig.mt5().anchor_tau == 150.0 and SleepConfig.mt5().max_iterations == 4000


def test_joint_forward_matches_one_pass_per_memory(stream):
    net0, theta_a, _, memories = stream
    finals = []
    for joint in (True, False):
        net = copy.deepcopy(net0)
        result = sleep_consolidate(list(net.parameters()), _policy(net), memories,
                                   _config(max_iterations=25, joint_forward=joint, anchor_strength=0.1),
                                   anchor_params=theta_a, progress=False)
        finals.append(([p.detach().clone() for p in net.parameters()], result))
    (a, ra), (b, rb) = finals
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(torch.tensor(ra.memory_losses), torch.tensor(rb.memory_losses), rtol=1e-5, atol=1e-7)


def test_per_memory_losses_equal_separate_losses(stream):
    from sr_imitation.core.memory import per_memory_losses

    net0, _, _, memories = stream
    gen = torch.Generator().manual_seed(1)
    batches = [m.sample(16, gen) for m in memories]
    joint = per_memory_losses(memories, _policy(net0), batches)
    separate = [m.loss(_policy(net0), b) for m, b in zip(memories, batches, strict=True)]
    torch.testing.assert_close(torch.stack(joint), torch.stack(separate))


def test_cosine_matrix_of_known_gradients():
    g = np.array([[3.0, 0.0, 0.0], [0.0, 2.0, 0.0], [-1.0, 1.0, 0.0], [0.0, 0.0, 0.0]])  # the last one is zero
    cos = np.array(cosine_matrix(g @ g.T))
    s = 1 / np.sqrt(2)
    expected = [[1, 0, -s, 0], [0, 1, s, 0], [-s, s, 1, 0], [0, 0, 0, 0]]
    np.testing.assert_allclose(cos, expected, atol=1e-12)


def test_the_sleep_records_its_memories_cosines_first_and_last(stream):
    """The cosine matrix Eq. 1 bargains over, at the first and the last iteration. At the first, the newest memory
    (skill b, stored from this very network) has loss and gradient 0: its row and column are 0; by the last, both
    memories pull: unit diagonal, symmetric, a cosine in [-1, 1] that is the one the solver saw."""
    net0, _, _, memories = stream
    net = copy.deepcopy(net0)
    result = sleep_consolidate(list(net.parameters()), _policy(net), memories, _config(), progress=False)
    first, last = (np.array(c) for c in result.cosines_first_last)
    assert first.shape == last.shape == (2, 2)
    np.testing.assert_allclose(np.diag(first), [1.0, 0.0], atol=1e-12)
    assert first[0, 1] == first[1, 0] == 0.0
    np.testing.assert_allclose(np.diag(last), 1.0, atol=1e-12)
    assert last[0, 1] == last[1, 0] and -1 <= last[0, 1] <= 1 and last[0, 1] != 0
    assert result.to_dict()["cosines_first_last"] == result.cosines_first_last


def test_the_newest_guard_stops_at_the_first_window_where_the_newest_loss_reaches_the_older_ones(stream):
    """C3 of the final-sleep screening: with ``newest_guard`` the sleep stops at the end of the first window whose
    mean newest-memory loss is at or above the older memories' (computed here from the full sleep's record); up to
    there it is the same sleep, bit for bit; without it nothing changes."""
    net0, _, _, memories = stream
    full_net, guarded_net = copy.deepcopy(net0), copy.deepcopy(net0)
    cfg = _config(max_iterations=600)
    full = sleep_consolidate(list(full_net.parameters()), _policy(full_net), memories, cfg, progress=False)
    losses = np.asarray(full.memory_losses)
    assert losses[0, 1] < losses[0, 0]  # the newest memory starts nearly met: its skill is the policy's own
    windows = [losses[i:i + 50].mean(axis=0) for i in range(0, len(losses), 50)]
    crossing = next(i for i, w in enumerate(windows) if w[1] >= w[0])  # two memories: the older mean is memory a's
    guarded = sleep_consolidate(list(guarded_net.parameters()), _policy(guarded_net), memories,
                                _config(max_iterations=600, newest_guard=True), progress=False)
    assert guarded.stop_reason == "newest_guard" and guarded.stop_iteration == 50 * (crossing + 1) < 600
    assert guarded.memory_losses == full.memory_losses[: guarded.stop_iteration]
    assert full.stop_reason == "max_iterations"


def test_the_newest_guard_needs_an_older_memory_to_compare_with(stream):
    """One memory: nothing to compare, the guard never stops the sleep."""
    net0, _, _, memories = stream
    net = copy.deepcopy(net0)
    result = sleep_consolidate(list(net.parameters()), _policy(net), memories[1:],
                               _config(max_iterations=100, newest_guard=True), progress=False)
    assert result.stop_reason == "max_iterations" and result.stop_iteration == 100
