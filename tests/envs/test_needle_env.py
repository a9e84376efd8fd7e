"""Needle environment: spaces, determinism, action handling, grasping, rendering, rewards."""

import gymnasium as gym
import numpy as np
import pytest

from sr_imitation.envs.needle import SKILL_NAMES, NeedleEnv, gym_id
from sr_imitation.envs.needle import geometry as G
from sr_imitation.envs.needle.skills import Skill

SIZE = 32


@pytest.fixture
def make_env():
    envs = []

    def _make(**kwargs):
        kwargs.setdefault("image_height", SIZE)
        kwargs.setdefault("image_width", SIZE)
        env = NeedleEnv(**kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


@pytest.mark.parametrize("skill", SKILL_NAMES)
def test_spaces_and_dtypes(skill):
    env = gym.make(gym_id(skill), image_height=SIZE, image_width=SIZE)
    try:
        assert env.spec.max_episode_steps == 300
        assert env.action_space == gym.spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32)
        obs, info = env.reset(seed=0)
        assert set(obs) == {"pixels", "agent_pos"}
        assert obs["pixels"].shape == (SIZE, SIZE, 3) and obs["pixels"].dtype == np.uint8
        assert obs["agent_pos"].shape == (35,) and obs["agent_pos"].dtype == np.float32
        assert env.observation_space.contains(obs)
        assert info["is_success"] is False
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert isinstance(reward, float) and reward < 0.0
        assert isinstance(info["is_success"], bool)
        assert env.unwrapped.task == skill
        state = obs["agent_pos"]
        np.testing.assert_allclose(state[14:21], state[7:14] - state[0:7], atol=1e-5)  # goal - cur
        assert state[13] == 0.0  # desired jaw is 0 (spec §2.1)
    finally:
        env.close()


def test_state_only_has_no_pixels(make_env):
    env = make_env(obs_type="agent_pos")
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"agent_pos"}


def test_camera_dict_for_lerobot(make_env):
    env = make_env(camera_dict=True)
    obs, _ = env.reset(seed=0)
    assert obs["pixels"]["wrist"].shape == (SIZE, SIZE, 3)


def test_active_arm_matches_stream():
    assert [Skill(s).active_arm for s in SKILL_NAMES] == [G.PSM2, G.PSM2, G.PSM2, G.PSM1, G.PSM1]


@pytest.mark.parametrize("skill", ["approach", "insert", "pullout"])
def test_determinism_by_seed(make_env, skill):
    a, b, c = make_env(skill=skill), make_env(skill=skill), make_env(skill=skill)
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    oc, _ = c.reset(seed=8)
    np.testing.assert_array_equal(oa["agent_pos"], ob["agent_pos"])
    np.testing.assert_array_equal(oa["pixels"], ob["pixels"])
    assert not np.allclose(oa["agent_pos"], oc["agent_pos"])
    rng = np.random.default_rng(0)
    for _ in range(5):
        action = rng.uniform(-1, 1, size=7)
        ra = a.step(action)
        rb = b.step(action)
        np.testing.assert_array_equal(ra[0]["agent_pos"], rb[0]["agent_pos"])
        assert ra[1] == rb[1]


def test_nan_action_is_a_clear_error(make_env):
    env = make_env(obs_type="agent_pos")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([0, 0, np.nan, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(6))


def test_out_of_range_actions_are_clipped(make_env):
    env = make_env(skill="approach", obs_type="agent_pos")
    obs0, _ = env.reset(seed=0)
    obs1, *_ = env.step(np.array([5.0, -3.0, 0.0, 10.0, 0.0, 0.0, 0.0]))
    delta = obs1["agent_pos"][:7] - obs0["agent_pos"][:7]
    np.testing.assert_allclose(delta[:3], [0.1, -0.1, 0.0], atol=1e-5)  # 1 mm in cm
    np.testing.assert_allclose(delta[3], np.radians(3.0), atol=1e-5)


def test_insert_forces_jaw_action_to_zero(make_env):
    env = make_env(skill="insert", obs_type="agent_pos")
    obs0, _ = env.reset(seed=0)
    obs1, *_ = env.step(np.array([0, 0, 0, 0, 0, 0, 1.0]))
    assert obs1["agent_pos"][6] == obs0["agent_pos"][6] == 0.0
    assert env.holder == G.PSM2


def test_grasp_carry_release_and_regrasp(make_env):
    env = make_env(skill="place", obs_type="agent_pos")
    env.reset(seed=3)
    assert env.holder == G.PSM2
    needle0 = env.needle_pose.copy()
    env.step(np.array([1.0, 0, 0, 0, 0, 0, 0]))  # carried: the needle follows the tool
    base_x = G.BASE_POSES[G.PSM2][:3, 0]
    np.testing.assert_allclose(env.needle_pose[:3, 3] - needle0[:3, 3], base_x * G.MM, atol=1e-9)
    for _ in range(5):  # open the jaw past 0.2 -> release
        env.step(np.array([0, 0, 0, 0, 0, 0, 1.0]))
    assert env.holder is None
    needle1 = env.needle_pose.copy()
    env.step(np.array([1.0, 0, 0, 0, 0, 0, 0]))
    np.testing.assert_array_equal(env.needle_pose, needle1)  # released: the needle stays
    for _ in range(6):  # close again, still near the grasp point -> weld
        env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))
    assert env.holder == G.PSM2


def test_closing_far_from_the_needle_does_not_grasp(make_env):
    env = make_env(skill="approach", obs_type="agent_pos")
    env.reset(seed=0)
    for _ in range(20):
        _, _, terminated, _, info = env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))
    assert env.holder is None and not terminated and not info["is_success"]


def test_rendered_image_varies_and_follows_the_tool(make_env):
    env = make_env(skill="approach")
    obs, _ = env.reset(seed=0)
    img0 = obs["pixels"].astype(np.int16)
    assert img0.std() > 5.0  # not a constant image
    for _ in range(5):
        obs, *_ = env.step(np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]))
    assert np.abs(obs["pixels"].astype(np.int16) - img0).mean() > 2.0
    scene = NeedleEnv(
        skill="approach", render_mode="rgb_array", render_height=48, render_width=64, obs_type="agent_pos"
    )
    try:
        scene.reset(seed=0)
        assert scene.render().shape == (48, 64, 3)
    finally:
        scene.close()


def test_sparse_reward(make_env):
    env = make_env(skill="regrasp", reward_type="sparse", obs_type="agent_pos")
    env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros(7))
    assert reward == -1.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"skill": "suture"},
        {"thresholds": "strict"},
        {"reward_type": "shaped"},
        {"obs_type": "rgb"},
        {"image_height": 0},
        {"step_limit": 0},
        {"render_mode": "human"},
    ],
)
def test_invalid_settings_raise_value_error(kwargs):
    with pytest.raises(ValueError):
        NeedleEnv(**kwargs)


def test_truncation_at_step_limit(make_env):
    env = make_env(skill="approach", obs_type="agent_pos", step_limit=3)
    env.reset(seed=0)
    for _ in range(2):
        assert env.step(np.zeros(7))[3] is False
    assert env.step(np.zeros(7))[3] is True
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(7))


def test_prepositioned_resets_stay_inside_setpoint_limits():
    env = NeedleEnv(skill="approach", obs_type="agent_pos")
    for skill in SKILL_NAMES:
        for seed in range(20):
            env.reset(seed=seed, options={"skill": skill})
            for arm in (0, 1):
                sp = env.setpoints[arm]
                assert np.all(sp >= G.SETPOINT_LOW) and np.all(sp <= G.SETPOINT_HIGH)
            assert np.all(env.goal[:6] >= G.SETPOINT_LOW[:6]) and np.all(env.goal[:6] <= G.SETPOINT_HIGH[:6])


def test_randomize_off_gives_the_nominal_scene(make_env):
    env = make_env(skill="pullout", obs_type="agent_pos", randomize=False)
    a, _ = env.reset(seed=1)
    b, _ = env.reset(seed=2)
    np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
