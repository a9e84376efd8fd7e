"""The ACT-SR stream gives the sleep of stage k the right checkpoints (Eq. 2 and the anchor).

At stage k >= 2 the gate of Eq. 2 needs theta_i^wake for i < k only (passing theta_k^wake too would make
c_k = ||theta - theta_k^wake|| = 0 at the start of sleep and keep the gate always on), and the anchor pulls
toward theta_{k-1}^sleep (theta_1^wake for k = 2). The test records what the stream passes to
``sleep_consolidate`` and compares it with the parameters it saw at the end of every wake and sleep.
"""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.substrates.act import substrate as substrate_module
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.stream.wiring import assert_sleep_wiring, clone, same, sleep_recorder
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config


def _full_buffer_losses(policy, memories) -> dict[str, list[float]]:
    with torch.no_grad():
        return {"losses": [float(m.loss(policy, {key: m.tensors[key] for key in m.buffer_keys})) for m in memories]}


@pytest.fixture(scope="module")
def recorded_stream(state_datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("wiring") / "stream"
    # A sleep long and fast enough to measurably lower the memory losses; the plateau rule cannot fire.
    cfg = tiny_stream_config(state_datasets, out, SKILLS, use_images=False,
                             sleep={"lr": 1e-3, "max_iterations": 20, "early_stop_window": 20})
    trainer = ACTTrainer(cfg, fake_env_factory)
    wakes, sleeps = [], []
    real_wake = substrate_module.wake_train

    def recording_wake(policy, *args, **kwargs):
        result = real_wake(policy, *args, **kwargs)
        wakes.append(clone(p for _, p in policy.deployed_named_parameters()))  # theta_i^wake
        return result

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(substrate_module, "wake_train", recording_wake)
        mp.setattr("sr_imitation.stream.substrate.sleep_consolidate", sleep_recorder(sleeps, _full_buffer_losses))
        trainer.run()
    names = [n for n, _ in trainer.policy.deployed_named_parameters()]
    return out, names, wakes, sleeps


def _checkpoint(out, names, k: int, phase: str) -> list[torch.Tensor]:
    state = load_file(str(out / f"skill_{k}_{SKILLS[k - 1]}" / phase / "pretrained_model" / "model.safetensors"))
    return [state[n] for n in names]


def test_stage_k_sleep_gets_the_k_minus_1_earlier_wake_snapshots_and_the_previous_sleep_as_anchor(recorded_stream):
    out, names, wakes, sleeps = recorded_stream
    assert_sleep_wiring(wakes, sleeps, SKILLS)
    for k, call in zip((2, 3), sleeps, strict=True):
        # ... as saved: the gate snapshots are the wake checkpoints, the anchor the previous stage's final one ...
        for i, snapshot in enumerate(call["wake_snapshots"], start=1):
            assert same(snapshot, _checkpoint(out, names, i, "wake")), (k, i)
        assert same(call["anchor"], _checkpoint(out, names, k - 1, "wake" if k == 2 else "sleep"))
        # The sleep's end is what the stage saved.
        assert same(call["end"], _checkpoint(out, names, k, "sleep"))


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
    """ACT's VAE encoder runs only in training: sleep neither moves it nor measures gate distances on it (otherwise
    it would get only the anchor pull and inflate c_i)."""
    out, names, wakes, sleeps = recorded_stream
    assert names and not any(n.startswith("model.vae_encoder") for n in names)
    for k in (2, 3):
        stage = out / f"skill_{k}_{SKILLS[k - 1]}"
        wake, sleep = (load_file(str(stage / p / "pretrained_model" / "model.safetensors")) for p in ("wake", "sleep"))
        vae = [n for n in wake if n.startswith("model.vae_encoder")]
        assert vae and all(torch.equal(wake[n], sleep[n]) for n in vae)  # untouched by sleep
        assert any(not torch.equal(wake[n], sleep[n]) for n in names)  # the deployed policy did move
