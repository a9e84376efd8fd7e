"""SR's options for issue 59's screening on the SAC substrate (``--method_options``: ``expert_memory``,
``reset_wake``) and the plateau rule measured against the memories' scale (``--sleep.early_stop_scale``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from sr_imitation.core.excitability import ExcitabilityConfig
from sr_imitation.core.sleep import SleepConfig, _plateaued
from sr_imitation.io import load_checked_safetensors
from sr_imitation.reporting.same_weights import same_files, verdict
from sr_imitation.stream.config import StreamSleepConfig
from sr_imitation.stream.methods.registry import METHODS
from sr_imitation.substrates.sac.config import EvalConfig
from sr_imitation.substrates.sac.trainer import SACTrainer
from tests.substrates.sac.test_trainer import SimulatedKillError, tiny_config

EVAL = EvalConfig(episodes=2, videos_per_skill=0)
STAGE2 = ("stages", "02_door-open")


def _actor(path):
    """The actor's weights and biases in a checkpoint (not its excitability state, which the sleep also updates)."""
    tensors, _ = load_checked_safetensors(path)
    return {n: t for n, t in tensors.items() if n.startswith("actor.") and n.endswith((".weight", ".bias"))}


def test_expert_memories_instead_of_the_critics_are_distilled_in_the_sleep(tmp_path):
    out = tmp_path / "instead"
    results = SACTrainer(tiny_config(out, eval=EVAL, method_options={"expert_memory": "instead"})).run()
    sleep = results["stages"][1]["sleep"]
    assert sleep["skills"] == ["reach", "door-open"]
    assert (out.joinpath(*STAGE2) / "expert.safetensors").is_file()
    first, last = sleep["initial_memory_losses"], sleep["final_memory_losses"]
    assert first[1] == pytest.approx(0.0, abs=1e-9)  # the sleep starts at door-open's own wake-end actor
    assert first[0] > 0.01 and last[0] < first[0]  # and pulls it towards reach's expert
    assert sleep["frozen_critic_value_before"] == []  # no frozen critic in this sleep


def test_expert_memories_beside_the_critics_bargain_over_both(tmp_path):
    results = SACTrainer(tiny_config(tmp_path / "beside", eval=EVAL,
                                     method_options={"expert_memory": "beside"})).run()
    sleep = results["stages"][1]["sleep"]
    assert sleep["skills"] == ["reach", "door-open", "reach", "door-open"]
    assert len(sleep["final_alpha"]) == 4 and len(sleep["frozen_critic_value_before"]) == 2
    assert sleep["initial_memory_losses"][3] == pytest.approx(0.0, abs=1e-9)


def test_a_run_with_expert_memories_killed_after_a_memory_resumes_to_the_same_weights(tmp_path):
    cfg = dict(eval=EVAL, method_options={"expert_memory": "beside"})
    full = tmp_path / "full"
    SACTrainer(tiny_config(full, **cfg)).run()

    def kill(k, phase):
        if (k, phase) == (1, "memory"):
            raise SimulatedKillError

    with pytest.raises(SimulatedKillError):
        SACTrainer(tiny_config(tmp_path / "killed", **cfg), after_phase=kill).run()
    SACTrainer(tiny_config(tmp_path / "killed", resume=True, **cfg)).run()
    a = _actor(full.joinpath(*STAGE2, "sleep", "agent.safetensors"))
    b = _actor((tmp_path / "killed").joinpath(*STAGE2, "sleep", "agent.safetensors"))
    assert all(torch.equal(a[n], b[n]) for n in a)


def test_reset_wake_learns_each_skill_afresh_and_sleeps_from_the_shared_actor(tmp_path):
    out = tmp_path / "reset"
    sleep = StreamSleepConfig.mt5(max_iterations=1, lr=1e-12, early_stop_window=5, fw_iterations=5, batch_size=16)
    SACTrainer(tiny_config(out, eval=EVAL, sleep=sleep, method_options={"reset_wake": True})).run()
    wake1 = _actor(out / "stages" / "01_reach" / "wake" / "agent.safetensors")
    wake2 = _actor(out.joinpath(*STAGE2, "wake", "agent.safetensors"))
    slept = _actor(out.joinpath(*STAGE2, "sleep", "agent.safetensors"))
    # one step at lr 1e-12 leaves the sleep where it started: the shared actor (stage 1's), not door-open's wake
    assert all(torch.allclose(slept[n], wake1[n], atol=1e-6) for n in wake1)
    assert any(not torch.allclose(slept[n], wake2[n], atol=1e-3) for n in wake2)
    plain = tmp_path / "plain"
    SACTrainer(tiny_config(plain, eval=EVAL, sleep=sleep)).run()
    plain_wake1 = _actor(plain / "stages" / "01_reach" / "wake" / "agent.safetensors")
    assert any(not torch.equal(plain_wake1[n], wake1[n]) for n in wake1)  # even the first wake is from fresh networks


def test_reset_wake_with_the_plain_actor_in_the_wake_makes_reset_and_distill_s_wakes(tmp_path, monkeypatch):
    """``sr_c_b1_pw`` (mt5_compare): SR's ``reset_wake`` and ``expert_memory: instead`` with wake excitability off
    make Reset & Distill's wakes and expert memories bit for bit, stage after stage (neither the sleep nor the
    distillation disturbs the wake's random streams), so a pair of such runs differs in the consolidation only; the
    consolidations themselves differ."""
    cls = METHODS["reset_distill"]
    monkeypatch.setattr(cls, "config", dataclasses.replace(cls.config, iterations=20, batch_size=16))
    sleep = StreamSleepConfig.mt5(max_iterations=4, early_stop_window=5, fw_iterations=5, batch_size=16)
    SACTrainer(tiny_config(tmp_path / "rd", eval=EVAL, sleep=sleep, method="reset_distill",
                           excitability=ExcitabilityConfig(enabled=False))).run()
    SACTrainer(tiny_config(tmp_path / "pw", eval=EVAL, sleep=sleep, excitability=ExcitabilityConfig(wake_enabled=False),
                           method_options={"reset_wake": True, "expert_memory": "instead"})).run()
    for stage in ("01_reach", "02_door-open"):
        rd, pw = (tmp_path / v / "stages" / stage for v in ("rd", "pw"))
        a, b = _actor(rd / "wake" / "agent.safetensors"), _actor(pw / "wake" / "agent.safetensors")
        assert set(a) == set(b) and all(torch.equal(a[n], b[n]) for n in a), stage
        ea, eb = (load_checked_safetensors(d / "expert.safetensors")[0] for d in (rd, pw))
        assert set(ea) == set(eb) and all(torch.equal(ea[n], eb[n]) for n in ea), stage
    a, b = (_actor(tmp_path.joinpath(v, *STAGE2, "sleep", "agent.safetensors")) for v in ("rd", "pw"))
    assert any(not torch.equal(a[n], b[n]) for n in a)
    # protocol W's premise as its command checks it: the files themselves, byte for byte
    rows = same_files(tmp_path / "rd", tmp_path / "pw")
    assert len(rows) == 4 and verdict(rows, complete=True), rows


def test_an_unknown_option_value_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"expert_memory must be one of \['off', 'instead', 'beside'\]"):
        SACTrainer(tiny_config(tmp_path / "bad", eval=EVAL, method_options={"expert_memory": "both"})).run()
    assert not (tmp_path / "bad").exists()


def test_the_plateau_rule_against_the_memories_scale(tmp_path):
    window = [-892.2] * 5 + [-891.7] * 5  # issue 59's seed-0 sleep: 0.06 % of the level, a plateau by the window
    config = SleepConfig(early_stop_window=5, early_stop_tol=1e-3)
    assert _plateaued(window, config)
    assert not _plateaued(window, config, scale=100.0)  # 0.5 of a gap of 100 is 0.5 %: not a plateau
    assert _plateaued(window, config, scale=1000.0)
    with pytest.raises(ValueError, match=r"sleep.early_stop_scale must be one of \['window', 'memory_scale'\]"):
        SleepConfig(early_stop_scale="critic")
    sleep = StreamSleepConfig.mt5(max_iterations=12, early_stop_window=5, fw_iterations=5, batch_size=16,
                                  early_stop_scale="memory_scale")
    results = SACTrainer(tiny_config(tmp_path / "scaled", eval=EVAL, sleep=sleep)).run()
    assert results["stages"][1]["sleep"]["early_stop_scale"] > 0
    with pytest.raises(ValueError, match=r"memory_scale measures the plateau rule on the frozen critics' scale; "
                                         r"method_options expert_memory=instead keeps none"):
        tiny_config(tmp_path / "expert", eval=EVAL, sleep=sleep, method_options={"expert_memory": "instead"})
    assert not (tmp_path / "expert").exists()
