"""A stream over your own data and environment.

Skills that are not needle skills (``pick``, ``place_cup``), datasets named by repo_id in a local LeRobot cache,
evaluation in a gymnasium env per skill, in a LeRobot env config per skill, or switched off (``--eval.env=none``:
memory losses and validation l1 instead of success). Every bad input is refused in one line naming its key, before
the first gradient and before anything is written.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    SettingsMismatchError,
    read_fingerprint,
    settings_digest,
    write_fingerprint,
)
from sr_imitation.substrates.act.cli import parse_train_args
from sr_imitation.substrates.act.data import DatasetMismatchError
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import (
    SETTINGS_ADDED,
    ACTTrainer,
    resume_fingerprint,
    stream_inputs,
    train_stream,
)
from tests.substrates.act.helpers import ACTION_DIM, STATE_DIM, make_skill_dataset, tiny_stream_config
from tests.substrates.act.test_resume_settings import check_resume

SKILLS = ["pick", "place_cup"]
GYM_IDS = {"pick": "SrTinyPick-v0", "place_cup": "SrTinyPlaceCup-v0"}


class TinyArmEnv(gym.Env):
    """A plain gymnasium env (``Box`` observation: taken as ``agent_pos``) with the tiny datasets' 6-d state and
    7-d action; success when the first state entry passes ``goal``."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, goal: float = 1.0, action_dim: int = ACTION_DIM, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
        self.action_space = gym.spaces.Box(-1, 1, (action_dim,), np.float32)
        self.render_mode = render_mode
        self.goal = goal
        self._state = np.zeros(STATE_DIM, np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._state = self.np_random.normal(size=STATE_DIM).astype(np.float32)
        return self._state.copy(), {"is_success": False}

    def step(self, action):
        self._state = self._state + 0.1 * np.resize(np.asarray(action, np.float32), STATE_DIM)
        success = bool(self._state[0] > self.goal)
        return self._state.copy(), 0.0, success, False, {"is_success": success}

    def render(self):
        return np.full((16, 16, 3), 128, np.uint8)


@pytest.fixture(scope="module", autouse=True)
def tiny_gym_envs():
    """Register the tiny envs as a user's package would (and one whose action does not fit the datasets)."""
    ids = {**{gym_id: {"goal": 1.0 + i} for i, gym_id in enumerate(GYM_IDS.values())},
           "SrTinyWideAction-v0": {"action_dim": 3}}
    for gym_id, kwargs in ids.items():
        gym.register(id=gym_id, entry_point=TinyArmEnv, kwargs=kwargs)
    yield
    for gym_id in ids:
        gym.registry.pop(gym_id, None)


@pytest.fixture(scope="module")
def own_datasets(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("own")
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i, image=False)
    return root


@pytest.fixture(scope="module")
def lerobot_cache(own_datasets, tmp_path_factory) -> Path:
    """A local LeRobot cache ($HF_LEROBOT_HOME) holding the datasets as user/<skill>."""
    import shutil

    cache = tmp_path_factory.mktemp("hf_lerobot")
    for skill in SKILLS:
        shutil.copytree(own_datasets / skill, cache / "user" / skill)
    return cache


@pytest.fixture
def offline_cache(lerobot_cache, monkeypatch) -> Path:
    """LeRobot resolves repo_ids in ``lerobot_cache``, and any download attempt fails the test."""
    monkeypatch.setattr("lerobot.datasets.dataset_metadata.HF_LEROBOT_HOME", lerobot_cache)

    def no_download(*args, **kwargs):
        raise AssertionError(f"tried to download {args} {kwargs}")

    monkeypatch.setattr("lerobot.datasets.lerobot_dataset.snapshot_download", no_download)
    return lerobot_cache


def _config(root: Path, out: Path, eval_cfg: EvalConfig, skills: list[str] = SKILLS, **stream):
    cfg = tiny_stream_config(root, out, skills, use_images=False)
    cfg.eval = eval_cfg
    for key, value in stream.items():
        setattr(cfg.stream, key, value)
    cfg.stream.__post_init__()
    cfg.__post_init__()
    return cfg


@pytest.fixture(scope="module")
def no_eval_run(lerobot_cache, tmp_path_factory):
    """A two-skill stream over repo_ids in the local cache, skills with no environment, ``--eval.env=none``."""
    mp = pytest.MonkeyPatch()
    mp.setattr("lerobot.datasets.dataset_metadata.HF_LEROBOT_HOME", lerobot_cache)
    try:
        out = tmp_path_factory.mktemp("none") / "run"
        cfg = _config(Path("unused"), out, EvalConfig(env="none", episodes=0),
                      repo_ids=[f"user/{s}" for s in SKILLS])
        yield out, cfg, train_stream(cfg)  # no environment factory: none is needed
    finally:
        mp.undo()


def test_a_stream_of_own_skills_without_evaluation_reports_memory_losses(no_eval_run):
    out, _, results = no_eval_run
    assert results["evaluation"] == "none" and results["skills"] == SKILLS and results["eval_units"] == 0
    for name in ("afsr", "prs", "bwt", "bwt_wake", "spi"):  # not measured: null, not 0
        assert results["metrics"][name]["final"] is None and results["metrics"][name]["curve"] == [None, None]
    assert results["success_matrix"] == [[None, None], [None, None]]
    losses = results["losses"]
    # M_i snapshots the policy right after wake i: its loss there is 0; after the next stage it is not
    assert losses["memory_loss_after_wake"][0][0] == pytest.approx(0.0, abs=1e-9)
    assert losses["memory_loss_after_wake"][1][1] == pytest.approx(0.0, abs=1e-9)
    assert losses["memory_loss"][1][0] > 0 and losses["memory_loss"][0][1] is None
    # the validation l1 right after each wake is the l1 its early stopping kept (restore=best)
    for i in range(2):
        assert losses["validation_l1_after_wake"][i][i] == pytest.approx(losses["wake_best_val_l1"][i], rel=1e-5)
    assert all(v > 0 for row in losses["validation_l1"] for v in row if v is not None)
    md = (out / "results.md").read_text()
    assert "Evaluation: none (--eval.env=none)" in md and "Memory loss" in md and "Validation l1" in md
    assert json.loads((out / "results.json").read_text())["evaluation"] == "none"
    assert not (out / "videos").exists() and not list(out.rglob("trajectories.safetensors"))
    eval_json = json.loads((out / "skill_2_place_cup" / "sleep" / "eval.json").read_text())
    assert set(eval_json["pick"]) >= {"memory_loss", "validation_l1"}


def test_repo_ids_resolve_in_the_local_cache_and_fingerprint_the_same_content(no_eval_run, own_datasets, offline_cache):
    out, cfg, _ = no_eval_run
    assert [cfg.stream.dataset_path(i) for i in range(2)] == [offline_cache / "user" / s for s in SKILLS]
    assert [cfg.stream.repo_id(i) for i in range(2)] == ["user/pick", "user/place_cup"]
    by_path = _config(own_datasets, out, EvalConfig(env="none", episodes=0),
                      dataset_paths=[own_datasets / s for s in SKILLS])
    assert stream_inputs(cfg) == stream_inputs(by_path)  # identified by content, wherever they are
    settings = read_fingerprint(out / FINGERPRINT_FILE)
    assert not any(k.startswith("stream.repo_ids") for k in settings)  # allow-listed like dataset_paths


def test_a_missing_repo_id_is_one_line_naming_it_and_the_path_looked_at(offline_cache, tmp_path):
    out = tmp_path / "out"
    cfg = _config(Path("unused"), out, EvalConfig(env="none", episodes=0), repo_ids=["user/pick", "user/missing"])
    with pytest.raises(DatasetMismatchError) as info:
        train_stream(cfg)
    message = str(info.value)
    assert message.startswith(f"stream.repo_ids[1]: 'user/missing' is not in the local LeRobot cache (looked at "
                              f"{offline_cache / 'user' / 'missing'}")
    assert "\n" not in message and not out.exists()


def test_a_gym_id_per_skill_evaluates_the_stream(own_datasets, tmp_path):
    out = tmp_path / "run"
    cfg = _config(own_datasets, out, EvalConfig(env="gym", gym_ids=[GYM_IDS[s] for s in SKILLS], episodes=2,
                                                seeds=[0], max_steps=6, videos_per_skill=1))
    results = train_stream(cfg)
    assert results["evaluation"] == "gym" and results["eval_units"] == 1
    s = results["success_matrix"]
    assert s[0][1] is None and all(0.0 <= x <= 1.0 for x in (s[0][0], s[1][0], s[1][1]))
    assert results["metrics"]["afsr"]["final"] is not None
    assert "Evaluation: gym (--eval.env)." in (out / "results.md").read_text()
    assert len(list((out / "videos").rglob("*.mp4"))) >= 2  # the recording env renders rgb_array frames
    assert results["spi_features"] == list(range(STATE_DIM))  # not the needle layout: every agent_pos entry


def _register_lerobot_env_type() -> None:
    """A LeRobot env type (``--eval.env_type=sr_tiny_arm``) whose tasks are the tiny gym ids."""
    from dataclasses import field

    from lerobot.envs.configs import EnvConfig

    if "sr_tiny_arm" in EnvConfig.get_known_choices():
        return

    @EnvConfig.register_subclass("sr_tiny_arm")
    @dataclass
    class TinyArmEnvConfig(EnvConfig):
        task: str | None = "SrTinyPick-v0"
        features: dict = field(default_factory=dict)

        @property
        def gym_id(self) -> str:
            return str(self.task)

        @property
        def gym_kwargs(self) -> dict:
            return {"render_mode": "rgb_array"}


def test_a_lerobot_env_config_per_skill_evaluates_the_stream(own_datasets, tmp_path):
    _register_lerobot_env_type()
    out = tmp_path / "run"
    cfg = _config(own_datasets, out, EvalConfig(env="lerobot", env_type="sr_tiny_arm", env_tasks=["SrTinyPick-v0"],
                                                episodes=2, seeds=[0], max_steps=4, videos_per_skill=1),
                  skills=SKILLS[:1])
    results = train_stream(cfg)
    assert results["evaluation"] == "lerobot" and 0.0 <= results["success_matrix"][0][0] <= 1.0


def _refused_before_writing(cfg, match: str, monkeypatch, error: type[Exception] = ValueError) -> None:
    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", lambda *a, **k: pytest.fail("trained"))
    with pytest.raises(error, match=match) as info:
        train_stream(cfg)
    assert "\n" not in str(info.value) and not cfg.output_dir.exists()


@pytest.mark.parametrize("eval_kwargs, match", [
    ({"env": "gym", "gym_ids": ["SrTinyPick-v0", "NoSuchEnv-v0"]},
     r"^eval.gym_ids\[1\] \(skill 'place_cup'\): gymnasium has no environment 'NoSuchEnv-v0'"),
    ({"env": "gym", "gym_ids": ["nosuchpackage/Pick-v0", "SrTinyPick-v0"]},
     r"^eval.gym_ids\[0\] \(skill 'pick'\): gymnasium has no environment 'nosuchpackage/Pick-v0'"),
    ({"env": "gym", "gym_ids": ["SrTinyPick-v0", "SrTinyWideAction-v0"]},
     r"^eval.gym_ids\[1\] \('SrTinyWideAction-v0', skill 'place_cup'\): its action space has shape \(3,\), the "
     r"datasets' 'action' has \(7,\)"),
    ({"env": "lerobot", "env_type": "nosuchtype"}, r"^eval.env_type: LeRobot knows no env type 'nosuchtype'; known: "),
    ({"env": "lerobot", "env_type": "needle"},  # the needle env config has no task 'pick'
     r"^eval.env_tasks \(null: each skill's name is its task\): needle env config for task 'pick': env.task must be "
     r"one of"),
    ({"env": "needle"}, r"^stream.skills: \['pick', 'place_cup'\] have no evaluation environment .*--eval.env=none"),
])
def test_an_evaluation_environment_that_does_not_exist_or_fit_is_refused_before_training(
        own_datasets, tmp_path, monkeypatch, eval_kwargs, match):
    cfg = _config(own_datasets, tmp_path / "out", EvalConfig(episodes=1, seeds=[0], max_steps=3, **eval_kwargs))
    _refused_before_writing(cfg, match, monkeypatch)


def test_a_lerobot_env_whose_observation_does_not_fit_the_datasets_is_refused(state_datasets, tmp_path, monkeypatch):
    """The needle env through LeRobot's own ``make_env`` (state only): its 35-d agent_pos is not the datasets' 6-d
    state, found before the first gradient."""
    cfg = _config(state_datasets, tmp_path / "out", EvalConfig(
        env="lerobot", env_type="needle", env_options={"obs_type": "agent_pos"}, episodes=1, videos_per_skill=0),
        skills=["approach", "place"])
    _refused_before_writing(cfg, r"^eval.env_tasks \(null: each skill's name is its task\) \(needle task 'approach', "
                                 r"skill 'approach'\): its 'observation.state' has shape \(35,\), the datasets' has "
                                 r"\(6,\)", monkeypatch)


@pytest.mark.parametrize("build, match", [
    (lambda root, out: _config(root, out, EvalConfig(env="gym", gym_ids=["SrTinyPick-v0"])),
     r"^eval.gym_ids: 1 entries for 2 skills \['pick', 'place_cup'\]"),
    (lambda root, out: _config(root, out, EvalConfig(env="lerobot", env_type="needle", env_tasks=["a", "b", "c"])),
     r"^eval.env_tasks: 3 entries for 2 skills"),
    (lambda root, out: _config(root, out, EvalConfig(env="none"), repo_ids=["user/pick"]),
     r"^stream.repo_ids: 1 repo_ids for 2 skills"),
    (lambda root, out: _config(root, out, EvalConfig(env="none"), repo_ids=["user/pick", "user/place_cup"],
                               dataset_paths=[root / s for s in SKILLS]),
     r"^stream.repo_ids and stream.dataset_paths both name the datasets"),
    (lambda root, out: _config(root, out, EvalConfig(env="none"), repo_ids=["user/pick", "/abs/place"]),
     r"^stream.repo_ids\[1\]: '/abs/place' is not a repo_id"),
    (lambda root, out: EvalConfig(episodes=0), r"^eval.episodes must be >= 1, got 0 \(--eval.env=none switches"),
    (lambda root, out: EvalConfig(env="gym"), r"^eval.gym_ids: --eval.env=gym needs one gymnasium id per skill"),
    (lambda root, out: EvalConfig(gym_ids=["A-v0"]), r"^eval.gym_ids is a setting of --eval.env=gym, not of "
                                                       r"--eval.env=needle"),
    (lambda root, out: EvalConfig(env="lerobot"), r"^eval.env_type: --eval.env=lerobot needs a LeRobot env type"),
    (lambda root, out: EvalConfig(env="none", env_options={"a": 1}), r"^eval.env_options is a setting of "
                                                                     r"--eval.env=gym\|lerobot"),
    (lambda root, out: EvalConfig(env="gym", gym_ids=["A-v0"], thresholds="surgicai"),
     r"^eval.thresholds is the needle environment's success preset"),
    (lambda root, out: EvalConfig(env="elsewhere"),
     r"^eval.env must be one of \['needle', 'metaworld', 'gym', 'lerobot', 'none'\]"),
])
def test_malformed_evaluation_and_dataset_settings_are_refused_when_parsed(own_datasets, tmp_path, build, match):
    with pytest.raises(ValueError, match=match) as info:
        build(own_datasets, tmp_path / "out")
    assert "\n" not in str(info.value) and not (tmp_path / "out").exists()


def test_the_command_line_takes_the_new_flags(tmp_path):
    cfg = parse_train_args(["--stream.skills=[pick,place_cup]", "--stream.repo_ids=[user/pick,user/place_cup]",
                            "--eval.env=none", "--eval.episodes=0", f"--output_dir={tmp_path / 'run'}"])
    assert (cfg.stream.repo_ids, cfg.eval.env, cfg.eval.episodes) == (["user/pick", "user/place_cup"], "none", 0)
    cfg = parse_train_args(["--stream.skills=[pick,place_cup]", "--eval.env=lerobot", "--eval.env_type=pusht",
                            "--eval.env_tasks=[PushT-v0,PushT-v0]", "--eval.env_options={obs_type: pixels_agent_pos}",
                            f"--output_dir={tmp_path / 'run'}"])
    assert (cfg.eval.env_type, cfg.eval.env_tasks, cfg.eval.env_options) == (
        "pusht", ["PushT-v0", "PushT-v0"], {"obs_type": "pixels_agent_pos"})
    cfg = parse_train_args(["--stream.skills=[pick]", "--eval.env=gym", "--eval.gym_ids=[my_pkg/Pick-v0]",
                            f"--output_dir={tmp_path / 'run'}"])
    assert cfg.eval.gym_ids == ["my_pkg/Pick-v0"]


def test_a_run_from_before_the_evaluation_settings_resumes_with_the_needle_env_only(state_datasets, tmp_path):
    """Runs fingerprinted before ``eval.env`` existed were evaluated on the needle env: their fingerprint lacks the
    new keys, which count as their defaults (:data:`SETTINGS_ADDED`); another evaluation is refused naming it."""
    out = tmp_path / "run"
    ACTTrainer(tiny_stream_config(state_datasets, out, ["approach", "place"], use_images=False)).run_dir.prepare()
    stored = read_fingerprint(out / FINGERPRINT_FILE)
    assert set(SETTINGS_ADDED) <= set(stored)
    # as an older run stored them (on this LeRobot: the stack key stays)
    settings = {k: v for k, v in stored.items() if k not in SETTINGS_ADDED or k.startswith("stack.")}
    write_fingerprint(out / FINGERPRINT_FILE, SettingsFingerprint(settings, settings_digest(settings)))
    cfg = tiny_stream_config(state_datasets, out, ["approach", "place"], use_images=False)
    cfg.resume = True
    check_resume(cfg, resume_fingerprint(cfg))  # no error
    cfg.eval = EvalConfig(env="none", episodes=0)
    with pytest.raises(SettingsMismatchError, match=re.escape('eval.env: "needle" -> "none"')):
        check_resume(cfg, resume_fingerprint(cfg))


def test_an_extension_keeps_the_evaluation_of_the_skills_it_imports(own_datasets, tmp_path):
    cfg = _config(own_datasets, tmp_path / "out", EvalConfig(env="gym", gym_ids=list(GYM_IDS.values())))
    substrate = ACTSubstrate(cfg)
    assert substrate.source_skills({"stream.skills": ["pick"], "eval.gym_ids": ["SrTinyPick-v0"]}) == ["pick"]
    with pytest.raises(ValueError, match=r"^eval.gym_ids: the run being extended evaluated its skills with "
                                         r"\['Other-v0'\], this stream's first 1 entries are \['SrTinyPick-v0'\]"):
        substrate.source_skills({"stream.skills": ["pick"], "eval.gym_ids": ["Other-v0"]})
