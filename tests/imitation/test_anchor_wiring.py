"""Issue 9: the ACT-SR stream gives the sleep of stage k the right checkpoints (Eq. 2 and the anchor).

At stage k >= 2 the gate of Eq. 2 needs theta_i^wake for i < k only (passing theta_k^wake too would make
c_k = ||theta - theta_k^wake|| = 0 at the start of sleep and keep the gate always on), and the anchor pulls
toward theta_{k-1}^sleep (theta_1^wake for k = 2). The test records what the stream passes to
``sleep_consolidate`` and compares it with the parameters it saw at the end of every wake and sleep.
"""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.imitation import substrate as substrate_module
from sr_imitation.imitation.stream import StreamTrainer
from sr_imitation.stream import engine as engine_module
from tests.imitation.conftest import SKILLS
from tests.imitation.helpers import fake_env_factory, tiny_stream_config


def _clone(tensors) -> list[torch.Tensor]:
    return [t.detach().clone() for t in tensors]


def _same(a, b) -> bool:
    return len(a) == len(b) and all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b, strict=True))


def _full_buffer_losses(policy, memories) -> list[float]:
    with torch.no_grad():
        return [float(m.loss(policy, {key: m.tensors[key] for key in m.buffer_keys})) for m in memories]


@pytest.fixture(scope="module")
def recorded_stream(state_datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("wiring") / "stream"
    # A sleep long and fast enough to measurably lower the memory losses; the plateau rule cannot fire.
    cfg = tiny_stream_config(state_datasets, out, SKILLS, use_images=False, sleep_lr=1e-3,
                             sleep_max_iterations=20, sleep_early_stop_window=20)
    trainer = StreamTrainer(cfg, fake_env_factory)
    wakes, sleeps = [], []
    real_wake, real_sleep = substrate_module.wake_train, engine_module.sleep_consolidate

    def recording_wake(policy, *args, **kwargs):
        result = real_wake(policy, *args, **kwargs)
        wakes.append(_clone(p for _, p in policy.deployed_named_parameters()))  # theta_i^wake
        return result

    def recording_sleep(params, policy, memories, config, anchor_params=None, wake_snapshots=(), **kwargs):
        params = list(params)
        call = {"start": _clone(params), "anchor": None if anchor_params is None else _clone(anchor_params),
                "wake_snapshots": [_clone(s) for s in wake_snapshots], "skills": [m.skill for m in memories],
                "losses_before": _full_buffer_losses(policy, memories), "kwargs": kwargs}
        result = real_sleep(params, policy, memories, config, anchor_params=anchor_params,
                            wake_snapshots=wake_snapshots, **kwargs)
        call.update(end=_clone(params), result=result, losses_after=_full_buffer_losses(policy, memories))
        sleeps.append(call)
        return result

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(substrate_module, "wake_train", recording_wake)
        mp.setattr(engine_module, "sleep_consolidate", recording_sleep)
        trainer.run()
    names = [n for n, _ in trainer.policy.deployed_named_parameters()]
    return out, names, wakes, sleeps


def _checkpoint(out, names, k: int, phase: str) -> list[torch.Tensor]:
    state = load_file(str(out / f"skill_{k}_{SKILLS[k - 1]}" / phase / "pretrained_model" / "model.safetensors"))
    return [state[n] for n in names]


def test_stage_k_sleep_gets_the_k_minus_1_earlier_wake_snapshots_and_the_previous_sleep_as_anchor(recorded_stream):
    out, names, wakes, sleeps = recorded_stream
    assert len(wakes) == 3 and len(sleeps) == 2
    for k, call in zip((2, 3), sleeps, strict=True):
        assert call["skills"] == SKILLS[:k]
        # The sleep starts at theta_k^wake ...
        assert _same(call["start"], wakes[k - 1])
        # ... the gate sees theta_i^wake for i < k: exactly k - 1 of them, those of skills 1..k-1, as saved ...
        assert len(call["wake_snapshots"]) == k - 1
        for i, snapshot in enumerate(call["wake_snapshots"], start=1):
            assert _same(snapshot, wakes[i - 1]), (k, i)
            assert _same(snapshot, _checkpoint(out, names, i, "wake")), (k, i)
        # ... so no c_i is 0 at the start of sleep (c_k would be), and the recorded c_i are those distances.
        distances = call["result"].anchor_distances
        assert len(distances) == k - 1 and min(distances) > 0
        for c, snapshot in zip(distances, call["wake_snapshots"], strict=True):
            expected = torch.sqrt(sum(((a - b) ** 2).sum() for a, b in zip(call["start"], snapshot, strict=True)))
            assert c == pytest.approx(float(expected), rel=1e-5)
        # The anchor is theta_{k-1}^sleep (theta_1^wake for k = 2): what the previous stage ended with.
        previous_end = wakes[0] if k == 2 else sleeps[k - 3]["end"]
        assert _same(call["anchor"], previous_end)
        assert _same(call["anchor"], _checkpoint(out, names, k - 1, "wake" if k == 2 else "sleep"))
        assert not _same(call["anchor"], call["start"])
        assert call["kwargs"]["is_final_skill"] is (k == len(SKILLS))
        # The sleep's end is what the stage saved.
        assert _same(call["end"], _checkpoint(out, names, k, "sleep"))


def test_sleep_lowers_the_full_buffer_losses_of_the_earlier_memories(recorded_stream):
    _, _, _, sleeps = recorded_stream
    for call in sleeps:
        result = call["result"]
        assert result.stop_iteration == 20 and result.stop_reason == "max_iterations"
        assert result.anchor_lambda > 0  # SurgicAI setting: anchor always on
        # M_k is the wake-end policy itself: zero loss before sleep; the earlier memories were forgotten.
        assert call["losses_before"][-1] == 0.0 and min(call["losses_before"][:-1]) > 0
        assert sum(call["losses_after"][:-1]) < sum(call["losses_before"][:-1]), call
        assert max(call["losses_after"]) < max(call["losses_before"]), call


def test_sleep_optimizes_the_deployed_policy_only(recorded_stream):
    """ACT's VAE encoder runs only in training: sleep neither moves it nor measures gate distances on it (issue 10;
    before, it got only the anchor pull and inflated c_i)."""
    out, names, wakes, sleeps = recorded_stream
    assert names and not any(n.startswith("model.vae_encoder") for n in names)
    for k in (2, 3):
        stage = out / f"skill_{k}_{SKILLS[k - 1]}"
        wake, sleep = (load_file(str(stage / p / "pretrained_model" / "model.safetensors")) for p in ("wake", "sleep"))
        vae = [n for n in wake if n.startswith("model.vae_encoder")]
        assert vae and all(torch.equal(wake[n], sleep[n]) for n in vae)  # untouched by sleep
        assert any(not torch.equal(wake[n], sleep[n]) for n in names)  # the deployed policy did move
