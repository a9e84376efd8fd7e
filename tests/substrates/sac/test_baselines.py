"""Every continual baseline end to end on a tiny two-skill SAC stream (issue: RL baselines on MT5): it runs through
the one engine, shapes the second wake (its numbers are in the wake record), never sleeps, and reports the bytes of
exactly the tensors it stores (wake-only: nothing)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.io import load_checked_safetensors
from sr_imitation.stream import METHODS
from sr_imitation.stream.methods.ewc import EWC, EWCConfig
from sr_imitation.substrates.sac.config import EvalConfig
from sr_imitation.substrates.sac.trainer import SACTrainer
from tests.substrates.sac.test_trainer import tiny_config

WAKE_NUMBERS = {"agem": "agem_projected", "nash_mtl": "weight_current", "pcgrad": "weight_current",
                "clear": "replayed"}


@pytest.mark.parametrize("method", ["ewc", "der", "agem", "clear", "nash_mtl", "pcgrad", "reset_distill",
                                    "progress_compress", "componet"])
def test_a_baseline_runs_end_to_end_on_sac(tmp_path, method, monkeypatch):
    if method == "ewc":
        monkeypatch.setattr(EWC, "config", type(EWC.config)(fisher_states=40))  # tiny: 40 states, not 2000
    if method in ("reset_distill", "progress_compress"):  # tiny: 20 distillation steps, not 2000
        cls = METHODS[method]
        monkeypatch.setattr(cls, "config", dataclasses.replace(cls.config, iterations=20, batch_size=16))
    trainer = SACTrainer(tiny_config(tmp_path / method, method=method,
                                        eval=EvalConfig(episodes=1, videos_per_skill=0)))
    results = trainer.run()
    completed = trainer.run_dir.progress["completed"]
    sleeps = {key for key in completed if key.endswith(".sleep")}
    distills = method in ("reset_distill", "progress_compress")
    assert sleeps == ({"1.sleep", "2.sleep"} if distills else set()) and results["method"] == method
    assert set(results["memory_bytes"]) == ({"door-open"} if method == "componet" else {"reach", "door-open"})
    kept = trainer.engine.memories + trainer.method.extra_memories(trainer.substrate, 2)
    assert results["memory_bytes_total"] == sum(m.nbytes() for m in kept) > 0
    assert sum(results["memory_kinds"].values()) == results["memory_bytes_total"]
    if method == "progress_compress":  # the knowledge base's Fisher after compression 1 (protecting skill 1)
        assert {type(m).__name__ for m in kept} == {"OutputDistillationMemory", "FisherMemory"}
    if method == "componet":  # no memory, a module per later skill; module 1 frozen after skill 1's wake
        assert trainer.engine.memories == [] and set(results["memory_kinds"]) == {"componet_module"}
        first, _ = load_checked_safetensors(trainer.substrate.stage_dir(0) / "wake" / "agent.safetensors")
        last, _ = load_checked_safetensors(trainer.substrate.stage_dir(1) / "wake" / "agent.safetensors")
        for name in ("actor.fc1.weight", "actor.fc2.bias", "actor.heads_mean.0.weight", "actor.attention.0.bias"):
            assert torch.equal(first[name], last[name]), name
        assert not torch.equal(first["actor.heads_mean.1.weight"], last["actor.heads_mean.1.weight"])
        # the agent's normalizer moves on in wake 2; module 1 keeps its end-of-wake statistics and acts with them,
        # so skill 1's evaluation after stage 2 repeats stage 1's exactly (same paired start, same actions)
        assert not torch.equal(first["normalizer.mean"], last["normalizer.mean"])
        assert torch.equal(last["actor.norm_mean"][0], first["normalizer.mean"])
        assert last["actor.norm_count"][0] == first["normalizer.count"] < last["actor.norm_count"][1]
        traj = [load_checked_safetensors(trainer.substrate.stage_dir(k) / "trajectories.safetensors")[0]["traj.reach"]
                for k in (0, 1)]
        assert torch.equal(traj[0], traj[1])
        assert trainer.substrate.agent.normalizer.count == last["normalizer.count"]  # the live one is back
        return
    kinds = {type(m).__name__ for m in trainer.engine.memories}
    assert kinds == {"ewc": {"FisherMemory"}, "der": {"OutputDistillationMemory"},
                     "clear": {"TransitionMemory"}, "reset_distill": {"OutputDistillationMemory"},
                     "progress_compress": {"OutputDistillationMemory"}}.get(method, {"CriticMemory"})
    if method in WAKE_NUMBERS:
        assert WAKE_NUMBERS[method] in completed["2.wake"]["wake"]["method"]
        assert "method" not in completed["1.wake"]["wake"]  # no past skill: the hooks had nothing to do


def test_sac_wake_only_stores_no_memory(tmp_path):
    cfg = tiny_config(tmp_path / "w", eval=EvalConfig(episodes=1, videos_per_skill=0))
    cfg.sleep.enabled = False
    trainer = SACTrainer(cfg)
    results = trainer.run()
    assert results["label"] == "wake_only" and results["memory_bytes_total"] == 0
    assert not any(key.endswith("memory") for key in trainer.run_dir.progress["completed"])


def test_a_methods_own_defaults_are_fingerprinted(tmp_path, monkeypatch):
    # EWC's lambda lives in the method's config, not the run's: a changed default must refuse a resume (and the
    # archive's reuse of a finished run) instead of changing results silently
    settings = tiny_config(tmp_path / "run", method="ewc").resume_fingerprint().settings
    assert settings["method_config.lam"] == 1.0 and settings["method_config.fisher_states"] == 2000
    options = tiny_config(tmp_path / "run", method="ewc", method_options={"lam": 100}).resume_fingerprint()
    assert options.settings["method_config.lam"] == 100
    sr = tiny_config(tmp_path / "sr").resume_fingerprint().settings  # SR's options, off by default
    assert sr["method_config.expert_memory"] == "off" and sr["method_config.reset_wake"] is False
    SACTrainer(tiny_config(tmp_path / "run", method="ewc")).run_dir.prepare()  # writes the fingerprint
    monkeypatch.setattr(EWC, "config", EWCConfig(lam=100.0))
    with pytest.raises(SettingsMismatchError, match=r"settings_fingerprint.json: .*method_config.lam: 1.0 -> 100.0"):
        SACTrainer(tiny_config(tmp_path / "run", method="ewc", resume=True)).run_dir.prepare()
