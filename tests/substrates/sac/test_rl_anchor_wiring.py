"""The SAC stream gives the sleep of stage k the right checkpoints (Eq. 2 and the anchor).

At stage k >= 2 (1-based) the gate of Eq. 2 needs theta_i^wake for i < k only (passing theta_k^wake too would
make c_k = 0 at the start of sleep and keep the gate always on), and the anchor pulls toward theta_{k-1}^sleep
(theta_1^wake for k = 2). The test records what the trainer passes to ``sleep_consolidate`` and compares it with
the actor parameters seen at the end of every wake and sleep, and with the wake snapshots the stages saved.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from sr_imitation.stream.config import StreamSleepConfig
from sr_imitation.substrates.sac import substrate as substrate_module
from sr_imitation.substrates.sac.config import (
    CriticMemoryConfig,
    EvalConfig,
    RLTrainConfig,
    SACConfig,
    StreamConfig,
    WakeConfig,
)
from sr_imitation.substrates.sac.trainer import SACTrainer
from tests.stream.wiring import assert_sleep_wiring, clone, same, sleep_recorder

SKILLS = ["reach-v3", "door-open-v3", "drawer-open-v3"]


def _config(out: Path) -> RLTrainConfig:
    return RLTrainConfig(
        output_dir=out, seed=5, stream=StreamConfig(skills=SKILLS), max_episode_steps=20,
        sac=SACConfig(hidden_dim=16, batch_size=16, utd_ratio=0.5, warmup_steps=20, buffer_size=2000),
        wake=WakeConfig(budget_scale=0.002),
        # tau = 150 (MT5): the gate is on for these small networks; 10 iterations, the plateau rule cannot fire.
        sleep=StreamSleepConfig.mt5(max_iterations=10, early_stop_window=10, batch_size=16),
        memory=CriticMemoryConfig(buffer_size=16, validation_chunk=5, validation_max_rounds=1),
        eval=EvalConfig(episodes=1, videos_per_skill=0), progress=False, plots=False,
    )


@pytest.fixture(scope="module")
def recorded_stream(tmp_path_factory):
    out = tmp_path_factory.mktemp("rl_wiring") / "run"
    trainer = SACTrainer(_config(out))
    wakes, sleeps = [], []
    real_wake = substrate_module.train_skill

    def recording_wake(agent, *args, **kwargs):
        result = real_wake(agent, *args, **kwargs)
        wakes.append(clone(agent.actor_parameters()))  # theta_i^wake
        return result

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(substrate_module, "train_skill", recording_wake)
        mp.setattr("sr_imitation.stream.substrate.sleep_consolidate", sleep_recorder(sleeps))
        trainer.run()
    saved = [trainer.substrate.parameters_at(k, "wake") for k in range(len(SKILLS))]
    return wakes, sleeps, saved


def test_stage_k_sleep_gets_the_k_minus_1_earlier_wake_snapshots_and_the_previous_sleep_as_anchor(recorded_stream):
    wakes, sleeps, saved = recorded_stream
    assert len(wakes) == 3 and len(sleeps) == 2
    for i, snapshot in enumerate(saved):  # each stage saved its own theta^wake
        assert same(snapshot, wakes[i]), i
    assert_sleep_wiring(wakes, sleeps, [s.removesuffix("-v3") for s in SKILLS])
    for k, call in zip((2, 3), sleeps, strict=True):
        is_final = k == len(SKILLS)
        # MT5: gate tau = 150 is open for these small networks; no anchor after the final skill.
        assert call["result"].anchor_lambda == (0.0 if is_final else 1e-2)
        assert call["result"].stop_iteration == 10 and not same(call["end"], call["start"])
