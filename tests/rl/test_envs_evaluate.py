"""The evaluation harness against code nobody here wrote: Meta-World's scripted policies and a random policy."""

from __future__ import annotations

import numpy as np
import pytest

from sr_imitation.rl.envs import ACT_DIM, MT5_STREAM, OBS_DIM, STREAMS, SkillEnv, stream_skills
from sr_imitation.rl.evaluate import evaluate_policy, random_policy, scripted_policy


@pytest.mark.parametrize("skill", MT5_STREAM)
def test_scripted_policy_succeeds_random_policy_fails(skill):
    """Over all 50 configurations (the population the uniform protocol samples from) Meta-World's own scripted
    policy reaches >= 0.9 (door-open: 46/50 = 0.92) and a random policy ~0."""
    with SkillEnv(skill, seed=0) as env:
        scripted = evaluate_policy(scripted_policy(skill), env, 50, seed=0, configurations=range(50))
        assert scripted.success_rate >= 0.9, (skill, scripted.summary())
        rand = evaluate_policy(random_policy(0), env, 5, seed=123)
        assert rand.success_rate <= 0.2, (skill, rand.summary())


def test_env_shapes_time_limit_and_configurations():
    with SkillEnv("reach-v3", seed=3, max_episode_steps=7) as env:
        obs = env.reset()
        assert obs.shape == (OBS_DIM,) and obs.dtype == np.float32
        configs = set()
        for _ in range(20):
            env.reset()
            configs.add(env.configuration)
        assert len(configs) > 5 and all(0 <= c < 50 for c in configs)
        env.reset()
        for t in range(7):
            step = env.step(np.zeros(ACT_DIM))
            assert not step.terminated
            assert step.truncated == (t == 6)


def test_same_seed_same_rollouts_and_final_step_mode():
    with SkillEnv("door-open-v3", seed=0, max_episode_steps=60) as env:
        a = evaluate_policy(random_policy(1), env, 2, seed=5, record_trajectories=True)
        b = evaluate_policy(random_policy(1), env, 2, seed=5, record_trajectories=True)
        for x, y in zip(a.trajectories, b.trajectories, strict=True):
            np.testing.assert_array_equal(x, y)
        assert a.trajectories[0].shape == (61, OBS_DIM)
        c = evaluate_policy(random_policy(1), env, 1, seed=5, success_mode="final_step")
        assert c.success_rate == 0.0


def test_streams_and_errors():
    assert stream_skills("mt5-reverse") == tuple(reversed(MT5_STREAM))
    assert len(STREAMS["mt8"]) == 8
    with pytest.raises(ValueError, match="unknown stream"):
        stream_skills("mt6")
    with pytest.raises(ValueError, match="v3"):
        SkillEnv("reach-v2")
