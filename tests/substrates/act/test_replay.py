"""Experience replay on ACT: the replayed half of every wake batch comes only from the stored buffers of
earlier skills, each of ``--memory.buffer_size`` demonstration frames (what a wake batch holds for them, SR's
memory's frames); the first skill has no replay; a tiny stream runs, reports its memory and resumes identically."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.core.memory import load_memory
from sr_imitation.stream import METHODS, StreamEngine
from sr_imitation.stream.methods.base import WakeStep
from sr_imitation.stream.methods.replay import DemonstrationMemory, ReplayConfig
from sr_imitation.stream.substrate import MethodSettings
from sr_imitation.substrates.act.data import sample_observation_buffer
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import train_stream
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config


def _frames(offset: float, n: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    """n distinct frames whose state and action values start at ``offset`` (so their origin is recognizable)."""
    return {"observation.state": offset + torch.rand(n, 3, generator=g),
            "action": offset + torch.rand(n, 4, 2, generator=g),
            "action_is_pad": torch.rand(n, 4, generator=g) > 0.7}


def _rows(frames: dict[str, torch.Tensor]) -> set[tuple[float, ...]]:
    """Each frame as one tuple over every key (state, action chunk, padding mask together)."""
    n = len(frames["action"])
    flat = torch.cat([frames[k].reshape(n, -1).float() for k in sorted(frames)], dim=1)
    return {tuple(row.tolist()) for row in flat}


def test_replay_mixes_only_the_stored_frames_of_earlier_skills_into_the_wake_batch():
    g = torch.Generator().manual_seed(0)
    buffers = [DemonstrationMemory(s, _frames(10.0 * (i + 1), 5, g)) for i, s in enumerate(SKILLS[:2])]
    current = {**_frames(100.0, 8, g), "next.reward": None}  # a wake batch carries keys ACT does not train on
    method = METHODS["replay"](MethodSettings(sleep=False))

    def step(k: int, seed: int = 3) -> WakeStep:
        return WakeStep(k, 0, [], None, current, torch.Generator().manual_seed(seed))

    method.begin_wake(0, [], None)
    assert method.wake_batch(step(0)) is current  # skill 1: nothing stored yet, nothing replayed

    for k in (1, 2):  # wake k + 1 replays R_1..R_k
        method.begin_wake(k, buffers[:k], None)
        seen = set()
        for seed in range(20):
            batch = method.wake_batch(step(k, seed))
            assert set(batch) == {"observation.state", "action", "action_is_pad"}
            assert all(len(v) == 16 for v in batch.values())  # as many replayed frames as current ones
            assert all(torch.equal(batch[key][:8], current[key]) for key in batch)  # the current batch, unchanged
            replayed = _rows({key: v[8:] for key, v in batch.items()})
            stored = [_rows(dict(b.tensors)) for b in buffers]
            assert replayed <= set().union(*stored[:k])  # only stored frames of earlier skills ...
            assert not replayed & _rows({key: current[key] for key in batch})  # ... never the current skill's
            seen |= {i for i in range(k) if replayed & stored[i]}
        assert seen == set(range(k))  # uniform over the union: every earlier buffer is drawn from
    one, two = (method.wake_batch(step(2, seed=5)) for _ in range(2))
    assert all(torch.equal(one[key], two[key]) for key in one)  # the wake's seeded generator decides the draw

    half = METHODS["replay"](MethodSettings(options={"replay_ratio": 0.5}))
    half.begin_wake(2, buffers, None)
    assert len(half.wake_batch(step(2))["action"]) == 12
    with pytest.raises(ValueError, match="replay_ratio"):
        ReplayConfig(replay_ratio=0.0)


def test_the_buffer_holds_buffer_size_frames_of_the_skill_as_a_wake_batch_holds_them(state_datasets, tmp_path):
    cfg = tiny_stream_config(state_datasets, tmp_path / "run", SKILLS[:2], use_images=False)
    cfg.output_dir.mkdir()
    substrate = ACTSubstrate(cfg, fake_env_factory)
    substrate.setup()
    data = substrate._skill_data(1)
    pool = data.train_indices + data.val_indices  # 3 episodes x 10 frames
    frames = substrate.demonstration_frames(1)
    assert cfg.memory.buffer_size == 16 < len(pool)
    assert {k: tuple(v.shape) for k, v in frames.items()} == {
        "observation.state": (16, 6), "action": (16, 4, 7), "action_is_pad": (16, 4)}
    wake_items = substrate.preprocessor({k: torch.stack([data.dataset[i][k] for i in pool]) for k in frames})
    every = _rows({k: wake_items[k].cpu() for k in frames})
    assert _rows(frames) <= every and len(_rows(frames)) == 16  # 16 distinct frames of this skill, as trained on
    sr_buffer = sample_observation_buffer(data, 16, ["observation.state"], substrate.phase_seed(1, "memory"))
    assert torch.equal(frames["observation.state"],
                       substrate.preprocessor(sr_buffer)["observation.state"].cpu())  # SR's memory's frames
    more = substrate.demonstration_frames(1, 40)  # more than the skill has: 40 draws with replacement
    assert len(more["action"]) == 40 and _rows(more) <= every


def test_replay_runs_a_tiny_act_stream_and_resumes_to_identical_weights(state_datasets, tmp_path, monkeypatch):
    replayed: list[dict[str, torch.Tensor]] = []
    cls = METHODS["replay"]
    original = cls.wake_batch

    def spy(self, step):
        batch = original(self, step)
        if step.stage == 1:
            replayed.append({k: v[len(step.batch["action"]):].clone() for k, v in batch.items()})
        else:
            assert batch is step.batch
        return batch

    monkeypatch.setattr(cls, "wake_batch", spy)
    out = tmp_path / "replay"
    cfg = tiny_stream_config(state_datasets, out, SKILLS[:2], use_images=False)
    cfg.method = "replay"
    results = train_stream(cfg, fake_env_factory)
    monkeypatch.setattr(cls, "wake_batch", original)

    memories = [load_memory(out / "memories" / f"skill_{i + 1}_{s}.replay.safetensors", skill=s)
                for i, s in enumerate(SKILLS[:2])]
    assert [(m.kind, m.size) for m in memories] == [("act_demonstrations", 16)] * 2
    assert not (out / "memories" / "skill_1_approach.safetensors").exists()  # no SR memory
    assert results["method"] == "replay" and results["metrics"]["afsr"]["final"] is not None
    total = sum(m.nbytes() for m in memories)
    assert results["memory_kinds"] == {"act_demonstrations": total}
    assert results["memory_bytes"] == {m.skill: m.nbytes() for m in memories}
    steps = 2 * 2  # epochs x steps per epoch of the tiny wake
    assert len(replayed) == steps and all(len(r["action"]) == 4 for r in replayed)  # batch 4 + 4 replayed
    assert _rows({k: torch.cat([r[k] for r in replayed]) for k in replayed[0]}) <= _rows(dict(memories[0].tensors))

    plain_cfg = tiny_stream_config(state_datasets, tmp_path / "plain", SKILLS[:2], use_images=False)
    plain_cfg.method = "sequential_bc"
    train_stream(plain_cfg, fake_env_factory)

    def weights(run, stage):
        return load_file(tmp_path / run / stage / "wake" / "pretrained_model" / "model.safetensors")

    first, second = weights("replay", "skill_1_approach"), weights("replay", "skill_2_place")
    assert all(torch.equal(first[n], t) for n, t in weights("plain", "skill_1_approach").items())  # no replay yet
    assert any(not torch.equal(second[n], t) for n, t in weights("plain", "skill_2_place").items())

    killed = tmp_path / "killed"
    run_phase = StreamEngine._run_phase

    def kill_at_second_wake(self, k, phase):
        if (k, phase) == (1, "wake"):
            raise KeyboardInterrupt("simulated kill")
        return run_phase(self, k, phase)

    monkeypatch.setattr(StreamEngine, "_run_phase", kill_at_second_wake)
    cfg = tiny_stream_config(state_datasets, killed, SKILLS[:2], use_images=False)
    cfg.method = "replay"
    with pytest.raises(KeyboardInterrupt):
        train_stream(cfg, fake_env_factory)
    monkeypatch.setattr(StreamEngine, "_run_phase", run_phase)
    cfg.resume = True
    resumed = train_stream(cfg, fake_env_factory)  # R_1 comes from its file now
    assert resumed["metrics"] == results["metrics"]
    final = weights("killed", "skill_2_place")
    assert all(torch.equal(final[n], t) for n, t in second.items())
