"""The evaluation harness against code nobody here wrote: Meta-World's scripted policies and a random policy;
SPI on the robot's own state checked with the same policies; paired evaluation configurations."""

from __future__ import annotations

import numpy as np
import pytest

from sr_imitation.core.metrics import policy_motion, subspace_preservation
from sr_imitation.envs.metaworld.tasks import (
    ACT_DIM,
    MT5_STREAM,
    OBS_DIM,
    STREAMS,
    SkillEnv,
    _benchmark,
    configurations,
    scripted_policy,
    stream_skills,
)
from sr_imitation.substrates.sac.evaluate import (
    SPI_FEATURES,
    evaluate_policy,
    evaluation_configurations,
    random_policy,
)


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


def test_the_configurations_built_once_are_meta_worlds_and_leave_numpys_generator_alone():
    """SkillEnv builds ``metaworld.MT1(skill, seed=task_seed)`` once a process (about 2 s each): what it reads from
    the cached build equals a fresh build's, other seeds give other configurations, and neither build nor a cached
    read moves numpy's global generator (so an environment made after either starts from the same state)."""
    import metaworld

    _benchmark.cache_clear()
    np.random.seed(11)
    before = np.random.get_state()[1].copy()
    first = configurations("drawer-open-v3", 0)
    assert np.array_equal(np.random.get_state()[1], before)
    fresh = metaworld.MT1("drawer-open-v3", seed=0)
    assert configurations("drawer-open-v3", 0) == first
    assert list(first) == list(fresh.train_tasks) and len(first) == 50
    assert _benchmark.cache_info().misses == 1  # built once
    assert configurations("drawer-open-v3", 1) != first
    assert np.array_equal(np.random.get_state()[1], before)
    with SkillEnv("drawer-open-v3", seed=2) as env:
        assert env.tasks == list(first) and type(env._env) is fresh.train_classes["drawer-open-v3"]


def test_streams_and_errors():
    assert stream_skills("mt5-reverse") == tuple(reversed(MT5_STREAM))
    assert len(STREAMS["mt8"]) == 8
    with pytest.raises(ValueError, match="unknown stream"):
        stream_skills("mt6")
    with pytest.raises(ValueError, match="v3"):
        SkillEnv("reach-v2")


@pytest.mark.parametrize("skill", ["reach-v3", "drawer-open-v3"])
def test_spi_on_the_robots_own_state(skill):
    """SPI of Meta-World's scripted expert against itself on other configurations is ~1 (measured 1.000 for both
    skills), of a policy that does not move 0 (hand and gripper stay put, measured variance ~1e-6 of the expert's),
    of a random policy 0.67. The random policy cannot score below 2/3: with d = 4 features two 3-d subspaces share
    at least 2 dimensions (the floor documented in core.metrics). With the whole observation (object and goal
    coordinates) the still policy scored 0.5-0.6 instead of 0."""
    with SkillEnv(skill, seed=0, max_episode_steps=100) as env:
        def motion(act, configurations):
            result = evaluate_policy(act, env, 0, seed=0, record_trajectories=True, configurations=configurations)
            assert result.trajectories[0].shape[1] == OBS_DIM
            return policy_motion(result.trajectories, SPI_FEATURES)

        reference = motion(scripted_policy(skill), [0, 1, 2, 3])
        expert = motion(scripted_policy(skill), [10, 11, 12, 13])
        still = motion(lambda obs: np.zeros(ACT_DIM, dtype=np.float32), [10, 11])
        rand = motion(random_policy(0), [10, 11, 12, 13])
    assert reference.shape[1] == 4
    assert subspace_preservation(reference, reference) == pytest.approx(1.0, abs=1e-12)
    assert subspace_preservation(reference, expert) >= 0.95
    assert subspace_preservation(reference, still) <= 0.01
    spi_random = subspace_preservation(reference, rand)
    assert 2 / 3 - 1e-6 <= spi_random <= subspace_preservation(reference, expert) - 0.2


def test_evaluation_configurations_are_paired_by_run_seed_and_skill():
    a = evaluation_configurations(3, "reach-v3", 20)
    assert a == evaluation_configurations(3, "reach", 20)  # skill identity, version suffix stripped
    assert a[:5] == evaluation_configurations(3, "reach-v3", 5)  # episode j's configuration does not depend on N
    assert all(0 <= c < 50 for c in a) and len(set(a)) > 5
    assert a != evaluation_configurations(4, "reach-v3", 20)
    assert a != evaluation_configurations(3, "door-open-v3", 20)
    with pytest.raises(ValueError, match="episodes"):
        evaluation_configurations(3, "reach-v3", 0)
