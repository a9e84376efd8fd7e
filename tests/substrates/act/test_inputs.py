"""Every dataset of a stream is opened and matched to the policy before the first gradient, and before anything
is written: a bad later dataset fails at once with one message naming the file, and leaves no run directory."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from sr_imitation.substrates.act.data import DatasetMismatchError
from sr_imitation.substrates.act.trainer import train_stream
from tests.substrates.act.helpers import damage, fake_env_factory, make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place", "insert"]


def _copy(state_datasets, root):
    for skill in SKILLS:
        shutil.copytree(state_datasets / skill, root / skill)
    return root


def _fails_before_writing(root, out, match, monkeypatch):
    # Training must not start: the wake loop is replaced by a tripwire.
    def tripwire(*args, **kwargs):
        raise AssertionError("training started before the inputs were checked")

    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", tripwire)
    with pytest.raises(DatasetMismatchError, match=match) as info:
        train_stream(tiny_stream_config(root, out, SKILLS, use_images=False), fake_env_factory)
    assert "\n" not in str(info.value)  # one line
    assert not out.exists()  # nothing written


def test_deleted_data_file_of_the_last_skill_is_named_before_training(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    parquet = next((root / "insert" / "data").rglob("*.parquet"))
    parquet.unlink()
    _fails_before_writing(root, tmp_path / "out", r"insert: missing or empty data files \['data/chunk-000", monkeypatch)


def test_deleted_episode_metadata_is_named_instead_of_a_hub_error(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    shutil.rmtree(root / "place" / "meta" / "episodes")
    _fails_before_writing(root, tmp_path / "out", r"place: incomplete LeRobot dataset, missing meta/episodes",
                          monkeypatch)


def test_missing_later_dataset_and_other_action_size_fail_before_training(state_datasets, tmp_path, monkeypatch):
    root = _copy(state_datasets, tmp_path / "d")
    shutil.rmtree(root / "insert")
    _fails_before_writing(root, tmp_path / "o1", r"insert: not a LeRobot dataset", monkeypatch)
    make_skill_dataset(root, "insert", 2, image=False, action_dim=5)
    _fails_before_writing(root, tmp_path / "o2", r"insert/meta/info.json: feature 'action' has shape \(5,\)",
                          monkeypatch)


def test_other_fps_is_refused(state_datasets, tmp_path, monkeypatch):
    import json

    root = _copy(state_datasets, tmp_path / "d")
    info = root / "place" / "meta" / "info.json"
    data = json.loads(info.read_text())
    data["fps"] = 30
    info.write_text(json.dumps(data))
    _fails_before_writing(root, tmp_path / "out", r"place/meta/info.json: fps 30 differs from the first skill's 10",
                          monkeypatch)


def test_a_skill_without_an_evaluation_environment_is_refused_before_training(state_datasets, tmp_path, monkeypatch):
    """A dataset for ``suture`` with no needle environment is refused before training, in one line naming
    ``stream.skills``, with nothing written (it used to train two stages, write 27 files, then die with a 49-line
    traceback)."""
    root = _copy(state_datasets, tmp_path / "d")
    shutil.copytree(root / "insert", root / "suture")
    out = tmp_path / "out"
    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", lambda *a, **k: pytest.fail("trained"))
    with pytest.raises(ValueError, match=r"stream.skills: \['suture'\] have no evaluation environment") as info:
        train_stream(tiny_stream_config(root, out, ["approach", "suture"], use_images=False))  # the needle env
    assert "\n" not in str(info.value) and not out.exists()


@pytest.mark.parametrize("env, skills, message", [
    ("metaworld", ["reach-v3", "dor-open-v3"], r"^eval.env_tasks \(null: each skill's name is its task\) \(skill "
                                               r"'dor-open-v3'\): 'dor-open-v3' is not a Meta-World v3 task; did you "
                                               r"mean 'door-open-v3'\?$"),
    ("needle", ["aproach", "place"], r"^stream.skills: \['aproach'\] have no evaluation environment"),
])
def test_a_misspelled_skill_is_named_as_such_before_any_dataset_is_read(tmp_path, env, skills, message):
    """With no dataset for a misspelled skill, the error names the skill (and a close task name), not a missing
    dataset folder: the names are checked before the datasets are read (they used to be read first)."""
    from sr_imitation.substrates.act.evaluate import EvalConfig
    from sr_imitation.substrates.act.mt_joint import run_mt_joint

    cfg = tiny_stream_config(tmp_path / "no_datasets", tmp_path / "out", skills, use_images=False)
    cfg.eval = EvalConfig(env=env, episodes=1, seeds=[0], max_steps=3, videos_per_skill=0)
    for run in (train_stream, run_mt_joint):
        with pytest.raises(ValueError, match=message) as info:
            run(cfg)
        assert "\n" not in str(info.value) and "not a LeRobot dataset" not in str(info.value)
        assert not cfg.output_dir.exists()


@pytest.mark.parametrize("env, skills, present, record", [
    ("needle", SKILLS, ["approach", "place"], "sr-record --root={root} --skills=[insert]"),
    ("metaworld", ["reach-v3", "door-open-v3"], [], "sr-record --env=metaworld --root={root} "
                                                    "--skills=[reach-v3,door-open-v3]"),
])
def test_datasets_not_recorded_yet_get_the_command_that_records_them(state_datasets, tmp_path, env, skills,
                                                                      present, record):
    """A skill whose dataset folder does not exist, in a stream evaluated in one of the recorders' environments:
    the one line names the folder and the ``sr-record`` command for exactly the missing skills, for the stream and
    the MT-Joint oracle alike; nothing is written."""
    from sr_imitation.substrates.act.evaluate import EvalConfig
    from sr_imitation.substrates.act.mt_joint import run_mt_joint

    root = tmp_path / "d"
    root.mkdir()
    for skill in present:
        shutil.copytree(state_datasets / skill, root / skill)
    cfg = tiny_stream_config(root, tmp_path / "out", skills, use_images=False)
    cfg.eval = EvalConfig(env=env, episodes=1, seeds=[0], max_steps=3, videos_per_skill=0)
    first_missing = next(s for s in skills if s not in present)
    expected = (f"{root / first_missing}: not a LeRobot dataset (missing {root / first_missing}/meta/info.json); "
                f"to record them: {record.format(root=root)} (")
    for run in (train_stream, run_mt_joint):
        with pytest.raises(DatasetMismatchError) as info:
            run(cfg)
        assert str(info.value).startswith(expected) and "\n" not in str(info.value)
        assert not cfg.output_dir.exists()


def test_datasets_given_by_path_or_evaluated_elsewhere_get_no_guess(tmp_path):
    """No ``sr-record`` hint where the recorders cannot know the data: datasets given by path, or a stream evaluated
    in the user's own environment (``--eval.env=none`` here)."""
    from sr_imitation.substrates.act.evaluate import EvalConfig

    cfg = tiny_stream_config(tmp_path / "d", tmp_path / "out", SKILLS, use_images=False)
    cfg.eval = EvalConfig(env="none")
    with pytest.raises(DatasetMismatchError, match=r"approach: not a LeRobot dataset") as info:
        train_stream(cfg)
    assert "sr-record" not in str(info.value)
    cfg = tiny_stream_config(tmp_path / "d", tmp_path / "out", SKILLS, use_images=False)
    cfg.stream.dataset_paths = [tmp_path / "d" / s for s in SKILLS]
    with pytest.raises(DatasetMismatchError, match=r"approach: not a LeRobot dataset") as info:
        train_stream(cfg)
    assert "sr-record" not in str(info.value) and not cfg.output_dir.exists()


@pytest.mark.parametrize("key, value, message", [
    ("optimizer_lr", -3e-4, "policy.optimizer_lr must be > 0, got -0.0003"),
    ("optimizer_weight_decay", -1.0, "policy.optimizer_weight_decay must be >= 0"),
    ("dropout", 1.5, "policy.dropout must be in [0, 1)"),
])
def test_out_of_range_policy_numbers_are_refused_at_parse_time_with_their_prefix(tmp_path, key, value, message):
    """``--policy.optimizer_lr=-3e-4`` was refused by torch after four files were written; the corrected command
    then met "already exists". Now it is refused when the config is built, before any directory exists."""
    from tests.substrates.act.helpers import tiny_policy

    with pytest.raises(ValueError, match=re.escape(message)):
        tiny_stream_config(tmp_path, tmp_path / "out", SKILLS, use_images=False, **{key: value})
    assert not (tmp_path / "out").exists()
    assert tiny_policy(**{key: value}) is not None  # the policy alone stays LeRobot's (stock lerobot-train)


def test_sleep_and_sac_range_errors_name_the_key_with_its_prefix():
    from sr_imitation.core.sleep import SleepConfig
    from sr_imitation.substrates.sac.config import SACConfig

    with pytest.raises(ValueError, match=r"^sleep.anchor_strength must be >= 0, got nan$"):
        SleepConfig(anchor_strength=float("nan"))
    with pytest.raises(ValueError, match=r"^sac.actor_lr must be > 0, got -1.0$"):
        SACConfig(actor_lr=-1.0)


def test_use_amp_runs_the_wake_under_bfloat16_autocast(state_datasets, tmp_path, monkeypatch):
    """``--policy.use_amp=true`` was stored and ignored, then refused; now the wake's forward passes run under
    bfloat16 autocast (the validation l1 and the sleep in float32) and the weights stay float32."""
    import torch
    from safetensors.torch import load_file

    from lerobot_policy_act_sr import ACTSRPolicy

    seen: list[tuple[bool, bool]] = []
    forward = ACTSRPolicy.forward

    def spy(self, batch, *args, **kwargs):
        seen.append((self.training, torch.is_autocast_enabled("cpu")))
        return forward(self, batch, *args, **kwargs)

    monkeypatch.setattr(ACTSRPolicy, "forward", spy)
    runs = {}
    for amp in (False, True):
        cfg = tiny_stream_config(_copy(state_datasets, tmp_path / f"d{amp}"), tmp_path / f"out{amp}", SKILLS[:2],
                                 use_images=False, use_amp=amp)
        seen.clear()
        results = train_stream(cfg, fake_env_factory)
        assert {autocast for training, autocast in seen if training} == {amp}  # every wake update, and only then
        runs[amp] = results
    assert all(r["metrics"]["afsr"]["final"] is not None for r in runs.values())
    final = "skill_2_place/sleep/pretrained_model/model.safetensors"
    plain, amp = load_file(tmp_path / "outFalse" / final), load_file(tmp_path / "outTrue" / final)
    assert all(t.dtype == torch.float32 for t in amp.values())
    assert any(not torch.equal(plain[k], amp[k]) for k in plain)


def test_push_to_hub_is_checked_before_training_and_pushes_the_final_policy(state_datasets, tmp_path, monkeypatch):
    """``--policy.push_to_hub=true`` exited 0 without pushing. Offline: one line naming the repo before anything is
    written; without a repo id: one line; reachable: the final consolidated checkpoint is uploaded with a card."""
    import huggingface_hub

    root = _copy(state_datasets, tmp_path / "d")
    out = tmp_path / "out"
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    cfg = tiny_stream_config(root, out, SKILLS[:2], use_images=False, push_to_hub=True, repo_id="me/sr_policy")
    with pytest.raises(ValueError, match=r"^policy.push_to_hub: cannot push me/sr_policy: .*HF_HUB_OFFLINE"):
        train_stream(cfg, fake_env_factory)
    assert not out.exists()
    with pytest.raises(ValueError, match=r"^policy.push_to_hub=true needs --policy.repo_id"):
        train_stream(tiny_stream_config(root, out, SKILLS[:2], use_images=False, push_to_hub=True),
                     fake_env_factory)
    assert not out.exists()
    uploads = []

    class FakeApi:  # the Hub itself cannot be reached from here: record what would be uploaded
        def whoami(self):
            return {"name": "me"}

        def create_repo(self, repo_id, private, exist_ok):
            return type("Repo", (), {"repo_id": repo_id})()

        def upload_folder(self, repo_id, repo_type, folder_path, commit_message, allow_patterns):
            uploads.append((repo_id, sorted(p.name for p in Path(folder_path).iterdir())))
            return type("Info", (), {"repo_url": f"https://huggingface.co/{repo_id}"})()

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(huggingface_hub, "HfApi", FakeApi)
    monkeypatch.setattr(huggingface_hub.ModelCard, "validate", lambda self, *a, **k: None)  # a Hub call too
    train_stream(cfg, fake_env_factory)
    assert len(uploads) == 1 and uploads[0][0] == "me/sr_policy"
    assert {"model.safetensors", "config.json", "README.md"} <= set(uploads[0][1])


@pytest.mark.parametrize("how", ["inverted", "truncated"])
def test_a_damaged_parquet_of_a_later_skill_is_named_before_anything_is_written(state_datasets, tmp_path, monkeypatch,
                                                                               how):
    """Before: stages 1-2 trained and 45 files were written, then two tracebacks ("Corrupt snappy compressed data",
    "Parquet magic bytes not found") that did not name the file."""
    root = _copy(state_datasets, tmp_path / "d")
    parquet = next((root / "insert" / "data").rglob("*.parquet"))
    damage(parquet, how)
    _fails_before_writing(root, tmp_path / "out", re.escape(str(parquet)) + ": unreadable parquet file", monkeypatch)


def test_a_damaged_video_is_named_before_anything_is_written(tmp_path):
    from sr_imitation.substrates.act.data import read_video_through
    from sr_imitation.video import write_mp4

    video = tmp_path / "episode.mp4"
    write_mp4(video, [np.full((16, 16, 3), i, dtype=np.uint8) for i in range(8)], fps=10)
    read_video_through(video)
    damage(video, "truncated")
    with pytest.raises(DatasetMismatchError, match=re.escape(str(video)) + ": "):
        read_video_through(video)


def _sr_train(capsys, root: Path, out: Path, skills: list[str], *flags: str) -> str:
    """``sr-train`` on the command line, refused: its one stderr line (exit status 2)."""
    from sr_imitation.infra.cli_errors import run_cli
    from sr_imitation.substrates.act.cli import train_main

    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        run_cli("sr-train", train_main, [f"--stream.dataset_root={root}", f"--stream.skills=[{','.join(skills)}]",
                                         f"--output_dir={out}", "--eval.env=none", "--policy.use_images=false",
                                         "--policy.device=cpu", "--progress=false", *flags])
    assert info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def _video(root: Path, skill: str) -> Path:
    return next((root / skill / "videos").rglob("*.mp4"))


def test_a_truncated_video_is_refused_before_the_first_phase_even_without_images(video_datasets, tmp_path,
                                                                                 monkeypatch, capsys):
    """Before: a truncated mp4 (``sr-record --video=true``; its index at the front, so it opens and demultiplexes)
    passed the check and 1-8 phases trained, also with ``--policy.use_images=false`` (LeRobot decodes every camera
    for each item), then ``IndexError: min(): Expected reduction dim 1``. Now every frame is decoded first: one line
    naming the file and the first episode and frame it lacks; nothing written."""
    root = tmp_path / "d"
    shutil.copytree(video_datasets, root)
    video = _video(root, "place")
    damage(video, "truncated")
    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", lambda *a, **k: pytest.fail("trained"))
    out = tmp_path / "out"
    line = _sr_train(capsys, root, out, ["approach", "place"])
    assert re.match(rf"sr-train: error: {re.escape(str(video))}: (unreadable video file \(.*\) after \d+ frames: )?"
                    r"episode \d, frame \d+ \(at [\d.]+ s\) is not in the video, which decodes \d+ frames", line), line
    assert not out.exists()


def _set_value(parquet: Path, column: str, row: int, element: int, value: float) -> None:
    """Write ``value`` into element ``element`` of ``column`` at ``row`` of a LeRobot data parquet (its schema, with
    LeRobot's metadata, kept)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(parquet)
    values = np.stack(table.column(column).to_numpy(zero_copy_only=False)).astype(np.float32)
    values[row, element] = value
    index = table.schema.get_field_index(column)
    field = table.schema.field(index)
    table = table.set_column(index, field, pa.array(list(values), type=field.type))
    pq.write_table(table, parquet)


@pytest.mark.parametrize("column, element, value", [("action", 3, float("nan")),
                                                    ("observation.state", 0, float("-inf"))])
def test_a_non_finite_number_is_refused_before_training_naming_file_episode_frame_and_column(
        state_datasets, tmp_path, monkeypatch, column, element, value):
    """Before: a NaN in one action of skill 3's parquet trained 8 phases, then two tracebacks
    (``NonFiniteLossError``). Now: one line naming the file, the column and its element, the episode and the
    frame, before anything is written."""
    root = _copy(state_datasets, tmp_path / "d")
    parquet = next((root / "insert" / "data").rglob("*.parquet"))
    _set_value(parquet, column, 14, element, value)  # 10 frames per episode: episode 1, frame 4
    message = (f"{parquet}: {value} in column '{column}[{element}]' at episode 1, frame 4 (row 14 of the file); "
               "a non-finite observation or action makes the losses NaN")
    _fails_before_writing(root, tmp_path / "out", "^" + re.escape(message), monkeypatch)


@pytest.mark.parametrize("relative, how", [("data", "truncated"), ("meta/episodes", "truncated"),
                                           ("meta/info.json", "truncated"), ("meta/stats.json", "truncated"),
                                           ("data", "footer")])
def test_a_damaged_file_is_named_on_the_command_line(state_datasets, tmp_path, monkeypatch, capsys, relative, how):
    """Before: refused, but the line ``sr-train`` printed was the innermost error, the parser's, which names no file
    ("Parquet magic bytes not found in footer", "Unterminated string starting at: line 65", "Expecting value").
    Now the line names the damaged file; nothing written."""
    root = _copy(state_datasets, tmp_path / "d")
    target = root / "place" / relative
    if target.is_dir():
        target = next(target.rglob("*.parquet"))
    if how == "footer":  # the footer's length and magic bytes
        data = bytearray(target.read_bytes())
        data[-8:-4] = b"\xff\xff\x00\x00"
        target.write_bytes(bytes(data))
    else:
        damage(target, how)
    monkeypatch.setattr("sr_imitation.substrates.act.substrate.wake_train", lambda *a, **k: pytest.fail("trained"))
    out = tmp_path / "out"
    line = _sr_train(capsys, root, out, SKILLS)
    kind = "JSON" if target.suffix == ".json" else "parquet"
    assert line.startswith(f"sr-train: error: {target}: unreadable {kind} file ("), line
    assert not out.exists()


def test_a_state_only_dataset_under_the_image_default_is_one_line_naming_the_file_and_the_flag(state_datasets,
                                                                                              tmp_path, capsys):
    """LeRobot's own ACT refuses inputs without a camera or an environment state ("You must provide at least one
    image ..."), so a LeRobot user expects an error, not a silent switch: ``sr-train`` on state-only datasets
    without ``--policy.use_images=false`` is one line naming the dataset's info.json and the flag, nothing written."""
    import sr_imitation.substrates.act.cli as imitation_cli
    from sr_imitation.infra.cli_errors import run_cli

    out = tmp_path / "run"
    with pytest.raises(SystemExit) as info:
        run_cli("sr-train", imitation_cli.train_main, [f"--stream.dataset_root={state_datasets}",
                                                       "--stream.skills=[approach,place]", f"--output_dir={out}"])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("sr-train: error:")]
    assert info.value.code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"sr-train: error: {state_datasets / 'approach' / 'meta' / 'info.json'}: no camera "
                               "feature; use --policy.use_images=false for state-only ACT"), lines[0]
    assert not out.exists()
