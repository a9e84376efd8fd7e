"""Reset & Distill on the ACT substrate (issue 59, item 5): a fresh ACT per skill, its action chunks on the skill's
stored frames (SR's memory kind and budget) distilled into the shared ACT after every skill; a tiny three-skill stream
without an evaluation environment (``--eval.env=none``: each skill's memory loss under the evaluated policy)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.core.memory import load_memory
from sr_imitation.stream.capabilities import ActorSnapshotMemory, ResettableNetworks
from sr_imitation.stream.methods.registry import refusal
from sr_imitation.stream.methods.reset_distill import ResetDistill
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import make_skill_dataset, tiny_stream_config

STREAM = SKILLS[:3]
STAGES = [f"skill_{k + 1}_{skill}" for k, skill in enumerate(STREAM)]
OPTIONS = {"iterations": 30, "batch_size": 8, "lr": 1e-3}
"""Tiny: 30 distillation steps (not the presets' 1000) at a learning rate that moves a tiny ACT in them."""


class StopError(Exception):
    pass


def _config(root: Path, out: Path):
    cfg = tiny_stream_config(root, out, STREAM, use_images=False)
    cfg.method, cfg.method_options = "reset_distill", dict(OPTIONS)
    cfg.eval = EvalConfig(env="none", episodes=0)
    return cfg


def _weights(out: Path, stage: str, phase: str) -> dict[str, torch.Tensor]:
    return load_file(str(out / stage / phase / "pretrained_model" / "model.safetensors"))


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)


@pytest.fixture(scope="module")
def run(state_datasets, tmp_path_factory):
    """The finished stream, its trainer (substrate) and the policy's weights as each wake started."""
    out = tmp_path_factory.mktemp("reset_distill") / "stream"
    trainer = ACTTrainer(_config(state_datasets, out))
    started: dict[int, dict[str, torch.Tensor]] = {}
    real_wake = trainer.substrate.wake

    def wake(k, memories, weight, method=None):
        started[k] = {n: t.detach().clone() for n, t in trainer.substrate.policy.state_dict().items()}
        assert memories == [] and weight == 0.0  # R&D's wake never distils from earlier memories
        return real_wake(k, memories, weight, method)

    trainer.substrate.wake = wake
    results = trainer.run()
    return out, trainer, results, started


def test_reset_distill_runs_on_act_with_its_capabilities_declared(run):
    out, trainer, results, _ = run
    assert refusal(ResetDistill, ACTSubstrate) is None
    assert isinstance(trainer.substrate, ResettableNetworks) and isinstance(trainer.substrate, ActorSnapshotMemory)
    assert results["method"] == "reset_distill"
    progress = json.loads((out / "progress.json").read_text())["completed"]
    for k in range(1, 4):  # a distillation after every skill, the first too
        assert {f"{k}.{p}" for p in ("wake", "memory", "wake.eval", "sleep", "sleep.eval")} <= set(progress)
        assert progress[f"{k}.sleep"]["stop_iteration"] == OPTIONS["iterations"]  # no early stop
        diag = json.loads((out / STAGES[k - 1] / "sleep" / "sleep_diagnostics.json").read_text())
        assert diag["skills"] == STREAM[:k] and diag["anchor_lambda"] == 0.0
        assert all(a == pytest.approx(1.0 / k) for a in diag["alpha"][-1])  # the plain mean of the losses
    # the expert memory is SR's kind and budget: the wake-end (expert's) chunks on --memory.buffer_size frames
    for k, skill in enumerate(STREAM):
        memory = load_memory(out / "memories" / f"{STAGES[k]}.safetensors", skill=skill)
        assert isinstance(memory, ActorMemory) and memory.size == 16
        assert memory.config["snapshot"] == f"{STAGES[k]}/wake"
    assert not list((out / "memories").glob("*.expert.safetensors"))


def test_each_wake_starts_from_a_fresh_seeded_network_and_the_random_state_is_left_alone(run):
    out, trainer, _, started = run
    substrate = trainer.substrate
    for k in range(3):
        before = torch.random.get_rng_state()
        substrate.reset_networks(k)
        assert torch.equal(torch.random.get_rng_state(), before)
        assert _same(started[k], substrate.policy.state_dict())  # seeded from (run seed, stage): reproducible
    assert not _same(started[1], started[2])  # a different network per stage
    for k in (1, 2):  # neither the shared policy nor the previous expert: every weight matrix is the fresh one's
        for phase in ("wake", "sleep"):
            previous = _weights(out, STAGES[k - 1], phase)
            matrices = [n for n, t in previous.items() if t.dim() == 2 and n.endswith("weight")]
            equal = [n for n in matrices if torch.equal(started[k][n], previous[n])]
            assert len(matrices) > 10 and not equal, (k, phase, equal)
    # the expert of stage 1 is trained from its reset, and the shared policy after stage 1 is that expert
    assert _same(_weights(out, STAGES[0], "wake"), _weights(out, STAGES[0], "sleep"))


def test_the_distillation_lowers_the_memories_losses_and_the_shared_policy_is_not_the_last_expert(run):
    out, trainer, _, _ = run
    substrate = trainer.substrate
    for k in (1, 2):  # the shared policy before stage k's distillation (the previous one's) and after it
        substrate.load_actor(k - 1, "sleep")
        before = [substrate._memory_loss(i) for i in range(k + 1)]
        substrate.load_actor(k, "sleep")
        after = [substrate._memory_loss(i) for i in range(k + 1)]
        assert sum(after) < 0.5 * sum(before), (k, before, after)
        assert after[k] < 0.5 * before[k]  # the new expert is learned by the shared policy
    # wake.eval measures the expert, sleep.eval the shared policy: on the earlier skills' memories the expert of the
    # last skill (a fresh network) is far off, the shared policy close
    wake = json.loads((out / STAGES[2] / "wake" / "eval.json").read_text())
    sleep = json.loads((out / STAGES[2] / "sleep" / "eval.json").read_text())
    for skill in STREAM[:2]:
        assert sleep[skill]["memory_loss"] < wake[skill]["memory_loss"], (skill, wake, sleep)
    assert not _same(_weights(out, STAGES[2], "wake"), _weights(out, STAGES[2], "sleep"))


def test_a_run_killed_after_any_phase_resumes_to_the_same_weights(run, state_datasets, tmp_path):
    reference, _, results, _ = run
    out = tmp_path / "killed"
    kills = [(0, "memory"), (1, "wake"), (1, "wake.eval"), (1, "sleep"), (2, "memory")]
    for kill in kills:  # killed after this phase, then resumed until the next kill

        def stop(k: int, phase: str, kill=kill) -> None:
            if (k, phase) == kill:
                raise StopError

        cfg = _config(state_datasets, out)
        cfg.resume = out.exists()
        with pytest.raises(StopError):
            ACTTrainer(cfg, after_phase=stop).run()
    cfg = _config(state_datasets, out)
    cfg.resume = True
    resumed = ACTTrainer(cfg).run()
    for stage in STAGES:
        for phase in ("wake", "sleep"):
            assert _same(_weights(out, stage, phase), _weights(reference, stage, phase)), (stage, phase)
    assert resumed["losses"] == results["losses"]


def test_load_actor_under_seen_statistics_gives_the_earlier_weights_in_the_statistics_in_use(tmp_path):
    """SR's ``reset_wake`` option, now on ACT too (``--stream.stats=seen`` supports SR): its sleep starts from the
    earlier checkpoint's policy, re-expressed into the current stage's statistics as ``parameters_at`` gives it."""
    root = tmp_path / "data"
    for i, skill in enumerate(STREAM[:2]):
        make_skill_dataset(root, skill, i, image=False, offset=3.0 * i)
    out = tmp_path / "sr_reset"
    cfg = tiny_stream_config(root, out, STREAM[:2], use_images=False, stats="seen")
    cfg.method_options = {"reset_wake": True}
    cfg.eval = EvalConfig(env="none", episodes=0)
    trainer = ACTTrainer(cfg)
    trainer.run()
    substrate = trainer.substrate
    substrate.load_actor(0, "wake")  # in the second skill's statistics now
    expected = substrate.parameters_at(0, "wake")
    loaded = substrate.trainable()
    assert all(torch.equal(a, b) for a, b in zip(loaded, expected, strict=True))
    stored = _weights(out, STAGES[0], "wake")
    names = [n for n, _ in substrate.policy.deployed_named_parameters()]
    assert any(not torch.equal(stored[n], p) for n, p in zip(names, loaded, strict=True))  # re-expressed
