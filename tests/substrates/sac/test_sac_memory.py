"""SAC agent, critic memory and sleep invariants."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sr_imitation.core.excitability import ExcitabilityConfig, ExcitableReLU
from sr_imitation.core.memory import load_memory
from sr_imitation.core.sleep import SleepConfig, anchor_coefficient, sleep_consolidate
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.io import CorruptFileError
from sr_imitation.substrates.sac.config import CriticMemoryConfig, SACConfig, SkillBudget, WakeConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory, sample_late_states, validate_critic
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent
from sr_imitation.substrates.sac.wake import should_stop_early

SMALL = SACConfig(hidden_dim=32, batch_size=16, buffer_size=1000)


def _filled_replay(n=200, seed=0):
    rng = np.random.default_rng(seed)
    rb = ReplayBuffer(1000)
    for _ in range(n):
        rb.add(rng.normal(size=OBS_DIM), rng.uniform(-1, 1, ACT_DIM), rng.uniform(0, 1), rng.normal(size=OBS_DIM),
               False)
    return rb


def _agent(seed=0, exc=None):
    torch.manual_seed(seed)
    agent = SACAgent(SMALL, exc or ExcitabilityConfig())
    agent.normalizer.update(np.random.default_rng(seed).normal(size=(50, OBS_DIM)))
    return agent


def _memory(agent, skill="reach", n=64, seed=0):
    states = np.random.default_rng(seed).normal(size=(n, OBS_DIM)).astype(np.float32)
    return CriticMemory.from_agent(skill, agent, states)


def test_critic_memory_gradient_reaches_only_the_actor():
    agent = _agent()
    memory = _memory(agent)
    agent.zero_grad(set_to_none=True)
    loss = memory.objective(agent.policy_fn, 32, torch.Generator().manual_seed(0))
    loss.backward()
    for name, p in agent.actor.named_parameters():
        if name.startswith("fc_log_std"):  # L_i uses the deterministic action tanh(mean): no std gradient
            assert p.grad is None or not p.grad.any()
        else:
            assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert all(p.grad is None for p in agent.critic.parameters())
    assert all(p.grad is None for p in agent.critic_target.parameters())
    assert agent.log_alpha.grad is None
    assert all(not t.requires_grad for t in memory.tensors.values())


def test_critic_memory_matches_live_critic_and_roundtrips(tmp_path):
    agent = _agent()
    memory = _memory(agent)
    s = memory.tensors["state"][:8]
    with torch.no_grad():
        a = agent.policy_fn(s)
        live = agent.critic.min_q(agent.normalizer(s).float(), a)
    torch.testing.assert_close(memory.q_value(s, a), live)
    path = memory.save(tmp_path / "m.safetensors")
    loaded = load_memory(path, skill="reach")
    assert isinstance(loaded, CriticMemory) and loaded.fingerprint() == memory.fingerprint()
    with pytest.raises(CorruptFileError, match="skill"):
        load_memory(path, skill="door-open")
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(CorruptFileError, match=str(path.name)):
        load_memory(path)


def _windowed_stop(objective, window, tol):
    """Where the documented rule stops: the first window boundary t >= 2w at which the mean objective of the
    last window differs from the previous window's by less than ``tol`` (relative); None if it never does."""
    for t in range(2 * window, len(objective) + 1, window):
        cur, prev = np.mean(objective[t - window : t]), np.mean(objective[t - 2 * window : t - window])
        if abs(cur - prev) / max(abs(prev), 1e-12) < tol:
            return t
    return None


def _two_critic_memories():
    agent = _agent()
    m1 = _memory(agent, "reach", seed=1)
    with torch.no_grad():  # a different critic for the second skill
        for p in agent.critic.parameters():
            p.add_(0.1 * torch.randn_like(p))
    m2 = _memory(agent, "door-open", seed=2)
    return agent, m1, m2


def test_sleep_leaves_frozen_critics_unchanged_and_moves_the_actor():
    agent, m1, m2 = _two_critic_memories()
    prints = [m1.fingerprint(), m2.fingerprint()]
    critic_before = [p.detach().clone() for p in agent.critic.parameters()]
    actor_before = [p.detach().clone() for p in agent.actor_parameters()]
    values_before = [m.value(agent.policy_fn) for m in (m1, m2)]
    cfg = SleepConfig.mt5(max_iterations=40, batch_size=16, fw_iterations=10)  # window 100: cannot stop early
    result = sleep_consolidate(agent.actor_parameters(), agent.policy_fn, [m1, m2], cfg, progress=False)
    assert result.stop_iteration == 40 and result.stop_reason == "max_iterations"
    assert result.skills == ["reach", "door-open"] and result.anchor_lambda == 0.0  # no anchor given
    assert len(result.alpha) == len(result.memory_losses) == len(result.sleep_objective) == 40
    # k = 2: Nash bargaining gives (1/2, 1/2) on the normalized gradients, every step.
    assert all(a == pytest.approx([0.5, 0.5], abs=1e-12) for a in result.alpha)
    # Sleep raised the value of every frozen critic (on its whole buffer) and the sampled losses fell.
    values_after = [m.value(agent.policy_fn) for m in (m1, m2)]
    assert all(a > b + 1e-3 for a, b in zip(values_after, values_before, strict=True)), (values_before,
                                                                                          values_after)
    losses = np.array(result.memory_losses)
    assert (losses[-10:].mean(0) < losses[:10].mean(0)).all()
    assert [m1.fingerprint(), m2.fingerprint()] == prints
    assert all(torch.equal(a, b) for a, b in zip(critic_before, agent.critic.parameters(), strict=True))
    assert any(not torch.equal(a, b) for a, b in zip(actor_before, agent.actor_parameters(), strict=True))


@pytest.mark.parametrize("tol", [0.07, 0.03])  # fires at the first check (t = 2w) / at a later one
def test_sleep_stops_where_the_windowed_rule_says(tol):
    agent, m1, m2 = _two_critic_memories()
    cfg = SleepConfig.mt5(max_iterations=40, batch_size=16, early_stop_window=5, early_stop_tol=tol)
    result = sleep_consolidate(agent.actor_parameters(), agent.policy_fn, [m1, m2], cfg, progress=False)
    predicted = _windowed_stop(result.sleep_objective, 5, tol)
    assert predicted is not None and predicted < 40  # the rule fired (before the budget) ...
    # ... exactly there: not earlier (the recorded objective would not allow it) and not later.
    assert result.stop_iteration == predicted == len(result.sleep_objective)
    assert result.stop_reason == "plateau"
    # The recorded objective is sum_i alpha_i L_i (no anchor here).
    for a, losses, objective in zip(result.alpha, result.memory_losses, result.sleep_objective, strict=True):
        assert objective == pytest.approx(float(np.dot(a, losses)), rel=1e-9, abs=1e-12)


def test_excitability_in_bounds_and_not_touched_by_optimizer():
    exc = ExcitabilityConfig()
    agent = _agent(exc=exc)
    gains = [m for m in agent.actor.modules() if isinstance(m, ExcitableReLU)]
    assert len(gains) == 2
    param_ids = {id(p) for g in agent.actor_optimizer.param_groups for p in g["params"]}
    assert all(id(m.excitability) not in param_ids and not m.excitability.requires_grad for m in gains)
    assert "excitability" not in dict(agent.actor.named_parameters())
    rb = _filled_replay()
    rng = np.random.default_rng(0)
    for _ in range(30):
        agent.update(rb.batch(rb.indices(16, rng)), excitability_rate=0.5)  # huge rate: hits the bounds
    for m in gains:
        e = m.excitability
        assert float(e.min()) >= exc.e_min - 1e-7 and float(e.max()) <= exc.e_max + 1e-7
        assert not torch.allclose(e, torch.ones_like(e))  # it did move, through Eq. 3 only
    # an optimizer step with zero rate leaves the gains exactly where they are
    before = [m.excitability.clone() for m in gains]
    agent.update(rb.batch(rb.indices(16, rng)), excitability_rate=0.0)
    assert all(torch.equal(b, m.excitability) for b, m in zip(before, gains, strict=True))


def test_anchor_gate_switches_at_tau():
    agent = _agent()
    params = agent.actor_parameters()
    snapshot = [p.detach().clone() for p in params]
    with torch.no_grad():
        params[0].add_(1.0)  # distance = sqrt(numel of first weight)
    distance = float(np.sqrt(params[0].numel()))
    lam, dist = anchor_coefficient(params, [snapshot], 1e-2, tau=distance + 0.01)
    assert lam == 1e-2 and dist[0] == pytest.approx(distance, rel=1e-5)
    lam, _ = anchor_coefficient(params, [snapshot], 1e-2, tau=distance - 0.01)
    assert lam == 0.0
    lam, _ = anchor_coefficient(params, [snapshot], 1e-2, tau=distance + 0.01, is_final_skill=True)
    assert lam == 0.0  # MT5: no anchor after the final skill


def test_sac_update_is_finite_and_alpha_clamped():
    agent = _agent()
    agent.log_alpha.data.fill_(10.0)
    rb = _filled_replay()
    info = agent.update(rb.batch(rb.indices(16, np.random.default_rng(0))))
    assert np.isfinite([info.critic_loss, info.actor_loss, info.alpha_loss]).all()
    assert float(agent.log_alpha.detach()) <= SMALL.log_alpha_max
    assert float(agent.actor.fc_log_std.bias.detach().mean()) == pytest.approx(-1.0, abs=0.01)


def test_critic_validation_and_late_state_sampling():
    agent = _agent()
    rb = _filled_replay(300)
    cfg = CriticMemoryConfig(buffer_size=40, validation_threshold=1e-9, validation_chunk=3, validation_max_rounds=2)
    report = validate_critic(agent, _filled_replay(50, seed=1), rb, cfg, np.random.default_rng(0))
    assert report["extra_updates"] == 6 and not report["passed"] and len(report["residuals"]) == 3
    starts = list(range(0, 300, 30))  # 10 episodes of 30 steps: the late 20% are steps 240..299
    states = sample_late_states(rb, starts, cfg, np.random.default_rng(0))
    late = {tuple(x) for x in rb.obs[240:300]}
    assert states.shape == (40, OBS_DIM) and all(tuple(x) in late for x in states)


def test_early_stopping_rule_and_budget_scaling():
    budget = SkillBudget(max_episodes=100, min_episodes=10, patience=5)
    flat = [1.0] * 20
    assert should_stop_early(flat, budget, window=3, improvement=0.02)
    assert not should_stop_early(flat[:9], budget, window=3, improvement=0.02)  # before min episodes
    rising = [1.0 + 0.1 * i for i in range(20)]
    assert not should_stop_early(rising, budget, window=3, improvement=0.02)
    wake = WakeConfig(budget_scale=0.01)
    assert wake.budget_for("door-open-v3") == SkillBudget(40, 10, 10)
    assert WakeConfig().budget_for("reach-v3") == SkillBudget(1500, 500, 500)
    with pytest.raises(ValueError):
        WakeConfig(budget_scale=0)
    with pytest.raises(ValueError):
        SACConfig(gamma=1.5)
