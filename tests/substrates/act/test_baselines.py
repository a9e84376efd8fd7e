"""Imitation baselines on the ACT substrate (issue: imitation baselines): LwF's target is the previous policy's
output, not the current one's; a tiny ACT stream per method runs through the engine's wake hooks."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.core.memory import load_memory
from sr_imitation.stream import METHODS
from sr_imitation.stream.methods.base import WakeStep
from sr_imitation.stream.substrate import MethodSettings
from sr_imitation.substrates.act.trainer import train_stream
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config


class _Policy:
    def __init__(self) -> None:
        self.net = torch.nn.Linear(3, 2)

    def chunk(self, batch):
        return self.net(batch["observation.state"])

    action_chunk = chunk


class _Substrate:
    """What LwF and M2Distill ask of a substrate (``PolicySnapshots``, ``IntermediateFeatures``): a frozen copy of the
    live policy, its weights and outputs, and its features."""

    def __init__(self, live: _Policy) -> None:
        self.live = live

    def frozen_policy(self) -> _Policy:
        frozen = type(self.live)()
        frozen.net.load_state_dict(self.live.net.state_dict())
        frozen.net.requires_grad_(False)
        return frozen

    def policy_weights(self):
        return dict(self.live.net.state_dict())

    def chunk_policy(self, batch):
        return self.live.chunk(batch)

    def chunk_and_features(self, batch):
        return self.live.action_chunk_and_features(batch)


def test_lwf_distils_toward_the_previous_policy_not_the_current_one():
    live = _Policy()
    method = METHODS["lwf"](MethodSettings(sleep=False))
    batch = {"observation.state": torch.randn(8, 3)}
    zero = torch.zeros(())
    method.begin_wake(0, [], _Substrate(live))
    assert method.wake_loss(zero, WakeStep(0, 0, list(live.net.parameters()), live.chunk, batch)) is zero  # skill 1
    method.begin_wake(1, [], _Substrate(live))
    step = WakeStep(1, 0, list(live.net.parameters()), live.chunk, batch)
    assert method.wake_loss(zero, step).item() == 0.0  # at the start of the wake: the previous policy is the current
    with torch.no_grad():
        live.net.weight.add_(0.3)
    expected = (live.chunk(batch) - (live.chunk(batch) - batch["observation.state"] @ torch.full((3, 2), 0.3))).pow(2)
    loss = method.wake_loss(zero, step)
    assert loss.item() > 0 and torch.isclose(loss, expected.mean())  # the target did not follow the policy
    loss.backward()
    assert live.net.weight.grad is not None and live.net.weight.grad.abs().sum() > 0


def test_lwf_and_m2distill_run_a_tiny_act_stream_and_change_only_the_later_wakes(state_datasets, tmp_path):
    runs = {}
    for method in ("lwf", "m2distill", "sequential_bc"):
        cfg = tiny_stream_config(state_datasets, tmp_path / method, SKILLS[:2], use_images=False)
        cfg.method = method
        runs[method] = train_stream(cfg, fake_env_factory)

    def weights(method, stage):
        return load_file(tmp_path / method / stage / "wake" / "pretrained_model" / "model.safetensors")

    plain = [weights("sequential_bc", s) for s in ("skill_1_approach", "skill_2_place")]
    for method in ("lwf", "m2distill"):
        first, second = (weights(method, s) for s in ("skill_1_approach", "skill_2_place"))
        snapshot = sum(t.numel() * t.element_size() for t in first.values())  # the teacher: one copy of the policy
        assert runs[method]["method"] == method and runs[method]["memory_kinds"] == {"policy_snapshot": snapshot}
        assert runs[method]["memory_bytes"] == {"approach": snapshot}
        assert all(torch.equal(first[n], plain[0][n]) for n in first)  # skill 1: nothing to distil from
        assert any(not torch.equal(second[n], plain[1][n]) for n in second)  # skill 2: the term acted
    lwf, m2 = weights("lwf", "skill_2_place"), weights("m2distill", "skill_2_place")
    assert any(not torch.equal(lwf[n], m2[n]) for n in lwf)  # the feature terms are not LwF's


def test_ewc_runs_a_tiny_act_stream_with_the_empirical_fisher(state_datasets, tmp_path, monkeypatch):
    import dataclasses

    from sr_imitation.stream.methods.ewc import EWC

    # lambda 1e6: a penalty the float32 loss can show after the tiny stream's few steps
    monkeypatch.setattr(EWC, "config", dataclasses.replace(EWC.config, fisher_states=4, lam=1e6))
    cfg = tiny_stream_config(state_datasets, tmp_path / "ewc", SKILLS[:2], use_images=False)
    cfg.method = "ewc"
    results = train_stream(cfg, fake_env_factory)
    memory = load_memory(tmp_path / "ewc" / "memories" / "skill_1_approach.ewc.safetensors", skill="approach")
    assert memory.kind == "ewc_fisher" and memory.config["states"] == 4
    fisher = [t for n, t in memory.tensors.items() if n.startswith("fisher.")]
    assert torch.sqrt(sum(f.pow(2).sum() for f in fisher)) == pytest.approx(1.0, abs=1e-5)
    assert results["memory_bytes_total"] == sum(m.nbytes() for m in [memory]) * 1 + results["memory_bytes"]["place"]
    assert results["memory_kinds"] == {"ewc_fisher": results["memory_bytes_total"]}
    # each epoch's record shows the loss the steps minimised: the policy's alone in the first wake (nothing to
    # anchor to), with the penalty on top in the second (the weights leave the anchor after the first step)
    first, second = (json.loads((tmp_path / "ewc" / stage / "wake" / "wake_history.json").read_text())["history"]
                     for stage in ("skill_1_approach", "skill_2_place"))
    assert all(r["loss"] == pytest.approx(r["bc_loss"], rel=1e-6) for r in first)
    assert all(r["loss"] > r["bc_loss"] for r in second), second


class _FeaturePolicy(_Policy):
    def action_chunk_and_features(self, batch):
        hidden = batch["observation.state"] * self.net.weight.sum()
        return self.net(batch["observation.state"]), {"state": hidden, "encoder": hidden.tanh()}


def test_m2distill_distils_actions_and_features_from_the_previous_policy():
    live = _FeaturePolicy()
    method = METHODS["m2distill"](MethodSettings(sleep=False))
    batch = {"observation.state": torch.randn(8, 3)}
    zero = torch.zeros(())
    method.begin_wake(0, [], _Substrate(live))
    assert method.wake_loss(zero, WakeStep(0, 0, list(live.net.parameters()), live.chunk, batch)) is zero
    method.begin_wake(1, [], _Substrate(live))
    step = WakeStep(1, 0, list(live.net.parameters()), live.chunk, batch)
    assert method.wake_loss(zero, step).item() == 0.0
    teacher_chunk, teacher = _Substrate(live).frozen_policy().action_chunk_and_features(batch)
    with torch.no_grad():
        live.net.weight.add_(0.3)
    chunk, feats = live.action_chunk_and_features(batch)
    expected = ((chunk - teacher_chunk).pow(2).mean() + (feats["state"] - teacher["state"]).pow(2).mean()
                + (feats["encoder"] - teacher["encoder"]).pow(2).mean())
    loss = method.wake_loss(zero, step)
    assert loss.item() > 0 and torch.isclose(loss, expected)  # action term + one term per feature
    live.net.bias.requires_grad_(False)
    loss.backward()  # the feature terms reach the weights (the bias only moves the action term)
    assert live.net.weight.grad.abs().sum() > 0


def test_sequential_bc_trains_the_same_whatever_the_memory_size(state_datasets, tmp_path):
    """Sequential BC never trains on a skill memory (any memory is drawn with its own phase seed, after the wake):
    ``--memory.buffer_size`` changes no weight and no success. (What lets a calibration step that only changes the
    memory size reuse the sequential BC and MT-Joint runs; MT-Joint builds no memory at all.)"""
    runs = {}
    for size in (8, 4):
        cfg = tiny_stream_config(state_datasets, tmp_path / f"m{size}", SKILLS[:2], use_images=False)
        cfg.method, cfg.memory.buffer_size = "sequential_bc", size
        cfg.sleep.enabled = False
        runs[size] = train_stream(cfg, fake_env_factory)
    for stage in ("skill_1_approach", "skill_2_place"):
        a, b = (load_file(tmp_path / f"m{s}" / stage / "wake" / "pretrained_model" / "model.safetensors")
                for s in (8, 4))
        assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)
    assert runs[8]["success_matrix"] == runs[4]["success_matrix"]
    stored = [json.loads((tmp_path / f"m{s}" / "train_config.json").read_text())["memory"]["buffer_size"]
              for s in (8, 4)]
    assert stored == [8, 4]  # the setting did reach each run
