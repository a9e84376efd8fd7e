"""Meta-World as a source of demonstrations and evaluation for the imitation substrate.

The gymnasium env (LeRobot's convention, Meta-World's own observation and success), ``sr-record --env=metaworld``
(scripted policies into LeRobot v3 datasets that LeRobot's own ``LeRobotDataset`` loads), the scripted policies
scored through the same evaluator as the learned policy, and a two-skill stream end to end with
``--eval.env=metaworld``; bad task names and dataset/environment mismatches are one line before anything is
written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sr_imitation.envs.metaworld.env import OBS_NAMES, UNSOLVED, MetaWorldEnv, unsolved_configurations
from sr_imitation.envs.metaworld.tasks import NUM_CONFIGURATIONS, OBS_DIM, SkillEnv, scripted_policy
from sr_imitation.recorders.metaworld import MetaWorldRecordConfig, record
from sr_imitation.substrates.act.evaluate import EvalConfig, evaluate_skills, make_env_factory, spi_features

TASKS = ["reach-v3", "button-press-topdown-v3"]


class ScriptedPolicy:
    """Meta-World's scripted policy behind the interface the evaluator drives (``select_action`` on a LeRobot
    batch), so the experts are scored by exactly the code that scores a learned policy."""

    def __init__(self, task: str) -> None:
        self.act = scripted_policy(task)

    def eval(self) -> None:
        pass

    def reset(self) -> None:
        pass

    def select_action(self, batch: dict) -> torch.Tensor:
        return torch.as_tensor(self.act(batch["observation.state"][0].numpy()))[None]


def test_the_observation_is_meta_worlds_own_with_named_entries():
    assert len(OBS_NAMES) == OBS_DIM == 39 and len(set(OBS_NAMES)) == 39
    env, raw = MetaWorldEnv("reach-v3"), SkillEnv("reach-v3")
    try:
        obs, info = env.reset(seed=123)
        assert set(obs) == {"agent_pos"} and obs["agent_pos"].shape == (39,) and info["is_success"] is False
        assert np.array_equal(obs["agent_pos"], raw.reset(env.configuration))  # the same 39 numbers, goal included
        assert env.observation_space.contains(obs)
        again, _ = env.reset(seed=123)
        assert np.array_equal(again["agent_pos"], obs["agent_pos"])  # the seed alone fixes the episode
    finally:
        env.close()
        raw.close()
    assert spi_features(39) == (0, 1, 2, 3)  # SPI reads the hand and the gripper


def test_demonstrable_only_never_draws_a_configuration_the_scripted_policy_cannot_solve():
    env = MetaWorldEnv("door-open-v3")
    try:
        drawn = set()
        for seed in range(300):
            env.reset(seed=seed)
            drawn.add(env.configuration)
        assert drawn == set(range(NUM_CONFIGURATIONS)) - set(UNSOLVED[("door-open-v3", 0)])
    finally:
        env.close()
    everything = MetaWorldEnv("door-open-v3", demonstrable_only=False)
    assert everything.configurations == list(range(NUM_CONFIGURATIONS))
    everything.close()


@pytest.mark.parametrize("task", ["door-open-v3", "reach-v3"])
def test_the_table_of_unsolved_configurations_is_what_the_scripted_policy_does(task):
    measured = unsolved_configurations(task, 0, max_steps=499)  # measured now (the table is for 500 steps)
    assert measured == UNSOLVED.get((task, 0), ())


def test_scripted_policies_succeed_through_our_evaluator(tmp_path):
    cfg = EvalConfig(env="metaworld", episodes=5, seeds=[0], max_steps=200, videos_per_skill=1, video_height=48,
                     video_width=64)
    make_env = make_env_factory(cfg, TASKS, None)
    for index, task in enumerate(TASKS):
        result = evaluate_skills(ScriptedPolicy(task), lambda b: b, lambda a: a, [task], [index], make_env, cfg,
                                 video_dir=tmp_path, progress=False)[task]
        assert result.success == 1.0
        assert max(result.episode_lengths) < 100
    import av

    videos = sorted(tmp_path.glob("*.mp4"))
    assert len(videos) == 2 and all("success" in p.name for p in videos)
    with av.open(str(videos[0])) as container:  # the configured video size, not the environment's own
        stream = container.streams.video[0]
        assert (stream.height, stream.width) == (48, 64)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("metaworld")
    record(MetaWorldRecordConfig(skills=TASKS, num_episodes=2, root=root, camera="corner2", image_size=16))
    return root


def test_recorded_datasets_load_with_lerobots_own_class(recorded):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for task in TASKS:
        ds = LeRobotDataset(f"local/sr_metaworld_{task}", root=recorded / task)
        assert ds.num_episodes == 2 and ds.meta.features["observation.state"]["shape"] == (39,)
        assert ds.meta.features["action"]["shape"] == (4,)
        frame = ds[0]
        assert frame["observation.images.corner2"].shape == (3, 16, 16) and frame["task"] == task
        last = ds.hf_dataset[len(ds) - 1]
        assert bool(last["next.success"]) and bool(last["next.done"])  # each episode ends at its success


def test_recording_is_byte_reproducible_and_quiet(recorded, tmp_path, capfd):
    import hashlib
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        record(MetaWorldRecordConfig(skills=TASKS[:1], num_episodes=2, root=tmp_path, camera="corner2",
                                     image_size=16))
    assert "Map:" not in capfd.readouterr().err  # no per-episode progress bar of Hugging Face datasets
    assert not [w for w in caught if "Converting input from bool" in str(w.message)]  # LeRobot's stats warning

    def digest(root: Path) -> dict[str, str]:
        return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(root.rglob("*")) if p.is_file()}

    assert digest(tmp_path / TASKS[0]) == digest(recorded / TASKS[0])


def test_a_bad_task_name_is_one_line_with_a_suggestion():
    with pytest.raises(ValueError, match=r"^skills\[0\]: 'reach-v2' is not a Meta-World v3 task; did you mean "
                                         r"'reach-v3'\?"):
        MetaWorldRecordConfig(skills=["reach-v2"])


def test_a_two_skill_stream_evaluates_in_metaworld(tmp_path_factory):
    from sr_imitation.substrates.act.trainer import train_stream
    from tests.substrates.act.helpers import tiny_stream_config

    root = tmp_path_factory.mktemp("mw_state")
    record(MetaWorldRecordConfig(skills=TASKS, num_episodes=2, root=root))
    out = tmp_path_factory.mktemp("mw_run") / "run"
    cfg = tiny_stream_config(root, out, list(TASKS), use_images=False)
    cfg.eval = EvalConfig(env="metaworld", episodes=1, seeds=[0], max_steps=5, videos_per_skill=1, video_height=32,
                          video_width=48)
    cfg.stream.pairs = "mt5"
    results = train_stream(cfg)
    assert results["evaluation"] == "metaworld" and results["skills"] == TASKS
    assert results["spi_features"] == [0, 1, 2, 3]
    assert results["metrics"]["afsr"]["final"] is not None
    assert len(list((out / "videos").rglob("*.mp4"))) >= 2


def test_a_skill_that_is_no_metaworld_task_is_refused_before_anything_is_written(tmp_path_factory):
    from sr_imitation.substrates.act.trainer import train_stream
    from tests.substrates.act.helpers import tiny_stream_config

    root = tmp_path_factory.mktemp("mw_bad")
    record(MetaWorldRecordConfig(skills=TASKS[:1], num_episodes=1, root=root))
    out = tmp_path_factory.mktemp("mw_bad_run") / "run"
    cfg = tiny_stream_config(root, out, [TASKS[0]], use_images=False)
    cfg.eval = EvalConfig(env="metaworld", env_tasks=["reach-v2"], episodes=1, seeds=[0], max_steps=5)
    with pytest.raises(ValueError, match=r"^eval\.env_tasks\[0\] \(skill 'reach-v3'\): 'reach-v2' is not a "
                                         r"Meta-World v3 task; did you mean 'reach-v3'\?"):
        train_stream(cfg)
    assert not out.exists()


def test_a_dataset_recorded_on_another_task_is_refused_naming_its_file(tmp_path_factory):
    from sr_imitation.substrates.act.trainer import train_stream
    from tests.substrates.act.helpers import tiny_stream_config

    root = tmp_path_factory.mktemp("mw_swap")
    record(MetaWorldRecordConfig(skills=TASKS, num_episodes=1, root=root))
    out = tmp_path_factory.mktemp("mw_swap_run") / "run"
    cfg = tiny_stream_config(root, out, list(TASKS), use_images=False)
    cfg.eval = EvalConfig(env="metaworld", env_tasks=list(reversed(TASKS)), episodes=1, seeds=[0], max_steps=5)
    with pytest.raises(ValueError, match=r"reach-v3/meta/sr_record\.json: the dataset of skill 'reach-v3' was "
                                         r"recorded on Meta-World task 'reach-v3', but it is evaluated on "
                                         r"'button-press-topdown-v3'"):
        train_stream(cfg)
    assert not out.exists()
