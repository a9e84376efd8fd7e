"""Offscreen rollout videos: files written and non-trivial, none when disabled, outcome unchanged, bad values."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest

from sr_imitation.envs.metaworld.tasks import SkillEnv, scripted_policy
from sr_imitation.envs.metaworld.video import SkillRenderer, VideoSpec, rendering_unavailable
from sr_imitation.substrates.sac.config import EvalConfig, RLTrainConfig
from sr_imitation.substrates.sac.evaluate import evaluate_policy, random_policy

pytestmark = pytest.mark.skipif(rendering_unavailable() is not None, reason="no offscreen rendering (EGL)")

STEPS = 10


def test_video_written_and_outcome_unchanged(tmp_path):
    with SkillEnv("door-open-v3", seed=0, max_episode_steps=STEPS) as env:
        plain = evaluate_policy(random_policy(1), env, 3, seed=5, record_trajectories=True)
        spec = VideoSpec(tmp_path / "v", episodes=2, height=64, width=64)
        filmed = evaluate_policy(random_policy(1), env, 3, seed=5, record_trajectories=True, video=spec)
    assert (filmed.successes, filmed.returns, filmed.lengths) == (plain.successes, plain.returns, plain.lengths)
    for a, b in zip(filmed.trajectories, plain.trajectories, strict=True):
        np.testing.assert_array_equal(a, b)
    assert [p.name for p in filmed.videos] == ["door-open_episode0_failure.mp4", "door-open_episode1_failure.mp4"]
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == [p.name for p in filmed.videos]  # no partials
    for path in filmed.videos:
        assert path.stat().st_size > 1000
        frames = np.stack(imageio.mimread(path))
        assert frames.shape == (STEPS + 1, 64, 64, 3)  # the frame after reset, then one per step
        assert frames.std() > 10  # a scene, not a blank image
        assert np.abs(frames[-1].astype(int) - frames[0]).max() > 50  # not constant: the arm moved


def test_success_named_and_zero_videos(tmp_path):
    with SkillEnv("reach-v3", seed=0, max_episode_steps=60) as env:
        res = evaluate_policy(scripted_policy("reach-v3"), env, 1, seed=0, configurations=[0],
                              video=VideoSpec(tmp_path / "ok", episodes=3, height=32, width=48))
        assert res.successes == [True] and [p.name for p in res.videos] == ["reach_episode0_success.mp4"]
        none = evaluate_policy(random_policy(0), env, 2, seed=0, video=VideoSpec(tmp_path / "none", episodes=0))
    assert none.videos == [] and not (tmp_path / "none").exists()


def test_renderer_upright_frame_and_close():
    with SkillEnv("reach-v3", seed=0, max_episode_steps=STEPS) as env:
        env.reset()
        with SkillRenderer(env, 48, 64) as renderer:
            img = renderer.frame()
        with pytest.raises(RuntimeError, match="close"):
            renderer.frame()
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    # upright: the uniform sky at the top, the tiled floor and robot base at the bottom
    assert img[:4].reshape(-1, 3).std(axis=0).max() < 2 and img[-4:].reshape(-1, 3).std(axis=0).max() > 10


@pytest.mark.parametrize(("overrides", "match"), [
    ({"videos_per_skill": -1}, "videos_per_skill"),
    ({"video_height": 0}, "video_height"),
    ({"video_width": 100}, "video_width"),
    ({"video_width": 4096}, "video_width"),
    ({"video_camera": "front"}, "video_camera"),
])
def test_bad_values_raise(overrides, match):
    with pytest.raises(ValueError, match=match):
        EvalConfig(**overrides)


def test_video_settings_not_in_resume_fingerprint(tmp_path):
    a = RLTrainConfig(output_dir=tmp_path, eval=EvalConfig(videos_per_skill=0))
    b = RLTrainConfig(output_dir=tmp_path, eval=EvalConfig(videos_per_skill=3, video_height=64))
    assert a.resume_fingerprint() == b.resume_fingerprint()
