"""``sr-train --resume``: every results-affecting setting is fingerprinted and checked before anything is written;
the allow-list is accepted; a copied run directory resumes where it is.

Without this check, resuming with another sleep batch size (now ``--sleep.batch_size``), ``--policy.n_action_steps``
or sleep anchor gate (now ``--sleep.anchor_tau``) would exit 0 and mix settings within one run, and
``--policy.dim_feedforward`` would rewrite train_config.json before failing, after which every plain resume would
fail.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path
from typing import Any

import draccus
import pytest
import torch
from safetensors.torch import load_file

import sr_imitation.substrates.act.cli as cli
from sr_imitation.core.aggregation import AGGREGATORS
from sr_imitation.envs.needle.skills import THRESHOLD_PRESETS
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.fingerprint import (
    FINGERPRINT_FILE,
    SettingsFingerprint,
    SettingsMismatchError,
    diff_settings,
    is_allowed,
    read_fingerprint,
    settings_digest,
    write_fingerprint,
)
from sr_imitation.io import CorruptFileError, read_config_json
from sr_imitation.lerobot_compat import lerobot_version
from sr_imitation.stream import methods_for
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import (
    RESUME_ALLOW_LIST,
    ACTTrainer,
    TrainStreamConfig,
    resume_fingerprint,
    train_stream,
)
from tests.infra.test_fingerprint import assert_refused_naming, changed_values, leaves, tree_state, with_leaf
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config

STREAM = SKILLS[:2]
MAPPING = ["MEAN_STD", "MIN_MAX", "IDENTITY"]
CHOICES: dict[str, list[Any]] = {
    # strings with a small set of valid values: the other ones
    "method": methods_for(ACTSubstrate),
    "sleep.aggregator": sorted(AGGREGATORS),
    "policy.distill_reduction": ["mean", "sum"],
    "policy.backbone_norm": ["auto", "group", "frozen_batch"],
    "policy.feedforward_activation": ["relu", "gelu"],
    "policy.vision_backbone": ["resnet18", "resnet34"],
    "policy.normalization_mapping.VISUAL": MAPPING,
    "policy.normalization_mapping.STATE": MAPPING,
    "policy.normalization_mapping.ACTION": MAPPING,
    "stream.pairs": ["surgicai", "mt5", "all", "adjacent"],
    "stream.stats": ["first", "seen", "union"],
    "method_options": [{"lam": 100.0}, {"expert_memory": "beside"}],
    "sleep.early_stop_scale": ["memory_scale"],
    "wake.restore": ["best", "last"],
    "stream.video_backend": ["pyav", "torchcodec"],
    "eval.thresholds": sorted(THRESHOLD_PRESETS),
    "eval.env": ["needle", "metaworld", "gym", "lerobot", "none"],  # none alone is valid; gym, lerobot need keys
    # free strings and paths: another value
    "stream.repo_id_prefix": ["local/other_prefix"],
    "stream.dataset_root": ["/elsewhere/needle"],
    "stream.skills": [[*STREAM, "insert"]],
    # settings that are None in the tiny config: a value of their declared type
    "sleep.anchor_tau": [0.5],
    "policy.temporal_ensemble_coeff": [0.01],
    "policy.pretrained_path": ["outputs/other/pretrained_model"],
    "policy.pretrained_revision": ["v1.0"],
    "policy.pretrained_backbone_weights": ["ResNet18_Weights.IMAGENET1K_V1"],
    "policy.repo_id": ["user/act_sr"],
    "policy.private": [True],
    "policy.tags": [["sr"]],
    "policy.license": ["mit"],
    "stream.dataset_paths": [[f"/data/{s}" for s in STREAM]],
    "stream.extend_from": ["/runs/previous"],
    "eval.gym_ids": [[f"Tiny{s.capitalize()}-v0" for s in STREAM]],
    "eval.env_type": ["needle"],
    "eval.env_tasks": [list(STREAM)],
    "eval.env_options": [{"obs_type": "agent_pos"}],
}
COMPANIONS: dict[str, dict[tuple[str, ...], Any]] = {
    # ACT allows a temporal ensemble only with one action step per chunk: change both (the diff names both).
    "policy.temporal_ensemble_coeff": {("policy", "n_action_steps"): 1},
    # the stored run's method (sr) has no options: give them to a method that has them (the diff names both).
    "method_options": {("method",): "ewc"},
    # the environment keys belong to their --eval.env (checked at parse time), the registries only before training
    "eval.gym_ids": {("eval", "env"): "gym"},
    "eval.env_type": {("eval", "env"): "lerobot"},
    "eval.env_tasks": {("eval", "env"): "lerobot", ("eval", "env_type"): "needle"},
    "eval.env_options": {("eval", "env"): "lerobot", ("eval", "env_type"): "needle"},
    # acts only where the statistics change (refused at parse time with the tiny config's first)
    "stream.reexpress_inputs": {("stream", "stats"): "seen"},
}
SKIP: dict[str, str] = {
    "policy.type": "sr-train trains act_sr only: TrainStreamConfig.__post_init__ refuses any other policy type",
    "policy.n_obs_steps": "ACT handles one observation step only: ACTConfig.__post_init__ refuses any other value",
    "policy.device": "only cpu exists on the test machine and LeRobot turns an unavailable device into cpu at "
                     "parse time; test_a_run_made_on_another_device_is_refused covers it",
    "substrate": "sr-train dispatches on it; TrainStreamConfig refuses any other value than act at parse time",
    "sleep.seed": "set per stage from --seed by the substrate; any other value than 0 is refused at parse time",
}
ALLOWED_CHANGES: dict[str, Any] = {
    # one changed value per allow-list entry (the test fails if an entry has none)
    "output_dir": "/somewhere/else",
    "resume": True,
    "overwrite": True,
    "progress": True,
    "wandb": {"enable": True, "project": "other", "mode": "disabled"},
    "eval.videos_per_skill": 0,
    "eval.video_height": 64,
    "eval.video_width": 96,
    "wake.num_workers": 1,
    "wake.snapshot_every_s": 60.0,
    "policy.input_features": {"observation.state": {"type": "STATE", "shape": [6]}},
    "policy.output_features": {"action": {"type": "ACTION", "shape": [7]}},
    "policy.sleep": True,  # another name of sleep.enabled (true in the stored run): folded into it
    "policy.sleep_memory_size": 16,  # another name of memory.buffer_size (16 in the stored run)
    "allow_unhashed_inputs": True,
    "stream.dataset_root": "<moved>",  # the same datasets copied elsewhere (resolved in the test)
    "stream.dataset_paths": "<moved paths>",
    "stream.repo_ids": "<cached repo_ids>",  # the same datasets in a (temporary) local LeRobot cache
}


def check_resume(cfg, fingerprint) -> None:
    """The resume check of a run directory against ``fingerprint`` (what a resume of ``cfg`` runs first). The run is
    built without ``overwrite`` (a command line cannot ask for both, and StreamRun refuses the pair); ``fingerprint``
    is still ``cfg``'s."""
    run = ACTTrainer(dataclasses.replace(cfg, overwrite=False)).run_dir
    run.fingerprint = fingerprint
    run.check_settings_against_run()


def _weights(run: Path, phase: str = "skill_2_place/sleep") -> dict[str, torch.Tensor]:
    return load_file(str(run / phase / "pretrained_model" / "model.safetensors"))


def _parse(tree: dict[str, Any], tmp: Path, out: Path) -> TrainStreamConfig:
    """The config a user gets from ``--config_path`` with ``tree`` (validation included), resuming ``out``: what
    ``draccus.parse`` does with a config file and no flags (decode the file's tree, defaults for what is missing,
    ``__post_init__`` validation), without building the argument parser (0.6 s per call)."""
    with cli.act_sr_choices_only():
        cfg = draccus.decode(TrainStreamConfig, json.loads(json.dumps(tree)))
    cfg.output_dir, cfg.resume = out, True
    return cfg


def test_decode_is_what_parse_gives_for_a_config_file(stored, tmp_path):
    out, saved = stored
    path = tmp_path / "requested.json"
    path.write_text(json.dumps(with_leaf(saved, ("sleep", "lr"), 0.5)))
    parsed = cli.parse_config(TrainStreamConfig, path, [])
    parsed.output_dir, parsed.resume = out, True
    assert resume_fingerprint(parsed) == resume_fingerprint(_parse(json.loads(path.read_text()), tmp_path, out))


@pytest.fixture(scope="module")
def stored(state_datasets, tmp_path_factory) -> tuple[Path, dict[str, Any]]:
    """A run directory as a fresh run leaves it before its first step: fingerprint + train_config.json."""
    out = tmp_path_factory.mktemp("stored") / "run"
    ACTTrainer(tiny_stream_config(state_datasets, out, STREAM, use_images=False)).run_dir.prepare()
    return out, read_config_json(out / "train_config.json")[0]  # as a person would write it: without the seal


@pytest.fixture(scope="module")
def reference(state_datasets, tmp_path_factory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("reference") / "run"
    return out, train_stream(tiny_stream_config(state_datasets, out, STREAM, use_images=False), fake_env_factory)


@pytest.fixture(scope="module")
def after_stage_1(state_datasets, tmp_path_factory) -> Path:
    """A run stopped after its first stage (as a kill between stages leaves it); tests work on copies."""
    out = tmp_path_factory.mktemp("stage1") / "run"
    ACTTrainer(tiny_stream_config(state_datasets, out, STREAM, use_images=False), fake_env_factory).run(
        stop_after=1)
    return out


@pytest.fixture
def fake_env_cli(monkeypatch):
    """``sr-train`` (train_main) with the fake environment instead of MuJoCo."""
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))


SR_OPTIONS = {"method_config.expert_memory", "method_config.reset_wake"}
"""SR's own settings with their defaults, from --method and --method_options (stream/methods/sleeping_robots.py)."""


def test_the_stored_files_hold_every_setting_but_not_the_run_location(stored):
    out, saved = stored
    assert saved["output_dir"] == "." and "resume" not in saved and "overwrite" not in saved
    settings = read_fingerprint(out / FINGERPRINT_FILE)
    assert str(out) not in (out / FINGERPRINT_FILE).read_text() + (out / "train_config.json").read_text()
    assert not any(is_allowed(k, RESUME_ALLOW_LIST) for k in settings)
    expected = {".".join(p) for p, _ in leaves(saved) if not is_allowed(".".join(p), RESUME_ALLOW_LIST)}
    inputs = {f"inputs.datasets.{skill}" for skill in STREAM}  # each dataset's content digest
    # + the method's own settings (sr: its options) and the LeRobot version the numbers are computed with
    assert set(settings) == expected | SR_OPTIONS | inputs | {"stack.lerobot"}
    assert settings["stack.lerobot"] == lerobot_version()
    assert all(len(settings[k]) == 64 for k in inputs)
    assert settings["method_config.expert_memory"] == "off" and settings["method_config.reset_wake"] is False
    assert {"sleep.batch_size", "policy.n_action_steps", "sleep.anchor_tau", "policy.dim_feedforward",
            "policy.optimizer_lr", "sleep.fw_iterations", "policy.distill_batch_size", "sleep.enabled",
            "memory.buffer_size", "substrate"} <= set(settings)
    for pattern in RESUME_ALLOW_LIST:  # no stale entries: each one names a setting of the config
        assert any(is_allowed(".".join(p), [pattern]) for p, _ in leaves(saved)) or pattern in ("resume",
                                                                                                "overwrite"), pattern


def test_every_fingerprinted_setting_changed_on_resume_is_refused_naming_it(stored, tmp_path):
    """Property test over the config's fields: each leaf setting outside the allow-list, changed alone (through a
    config file draccus parses and validates), is refused by the resume check with its key and values named."""
    out, saved = stored
    stored_settings = read_fingerprint(out / FINGERPRINT_FILE)
    covered, refused = set(), []
    for path, value in leaves(saved):
        key = ".".join(path)
        if is_allowed(key, RESUME_ALLOW_LIST):
            continue
        covered.add(key)
        if key in SKIP:
            continue
        tried = []
        for new in changed_values(key, value, CHOICES):
            tree = with_leaf(saved, path, new)
            for other, other_value in COMPANIONS.get(key, {}).items():
                tree = with_leaf(tree, other, other_value)
            try:
                cfg = _parse(tree, tmp_path, out)
            except Exception as exc:  # not a valid value of this setting: try the next candidate
                tried.append(f"{new!r}: {type(exc).__name__}")
                continue
            fingerprint = resume_fingerprint(cfg)
            if not diff_settings(stored_settings, fingerprint.settings):
                tried.append(f"{new!r}: parsed back to the stored value")
                continue
            before = tree_state(out)
            err = assert_refused_naming(lambda c=cfg, f=fingerprint: check_resume(c, f), key)
            assert tree_state(out) == before
            assert f"{FINGERPRINT_FILE}: cannot resume" in str(err)
            refused.append(key)
            break
        else:
            pytest.fail(f"{key} = {value!r}: no valid changed value ({tried}); add one to CHOICES or a reasoned SKIP")
    # every fingerprinted setting was visited; method_config is derived from --method and the method's defaults
    # (tests/substrates/sac/test_baselines.py::test_a_methods_own_defaults_are_fingerprinted)
    inputs = {k for k in stored_settings if k.startswith("inputs.datasets.")}  # test_inputs.py changes them
    # stack.lerobot is the installed LeRobot's version, not a setting: tests/test_lerobot_044_runs.py changes it
    assert covered | SR_OPTIONS | inputs | {"stack.lerobot"} == set(stored_settings) and len(inputs) == len(STREAM)
    assert set(SKIP) <= covered and len(refused) == len(covered) - len(SKIP) >= 60


def test_every_allow_listed_setting_changed_on_resume_is_accepted(stored, state_datasets, tmp_path, monkeypatch):
    out, saved = stored
    assert set(ALLOWED_CHANGES) == set(RESUME_ALLOW_LIST)
    moved = tmp_path / "moved"  # datasets are identified by content: the same bytes elsewhere resume
    shutil.copytree(state_datasets, moved)
    cache = tmp_path / "hf_lerobot"  # ... or in a local LeRobot cache, named by repo_id
    shutil.copytree(state_datasets, cache / "user")
    monkeypatch.setattr("lerobot.datasets.dataset_metadata.HF_LEROBOT_HOME", cache)
    resolved = {"<moved>": str(moved), "<moved paths>": [str(moved / s) for s in STREAM],
                "<cached repo_ids>": [f"user/{s}" for s in STREAM]}
    everything = saved
    for key, new in ALLOWED_CHANGES.items():
        new = resolved.get(new, new) if isinstance(new, str) else new
        path = tuple(key.split("."))
        cfg = _parse(with_leaf(saved, path, new), tmp_path, out)
        check_resume(cfg, resume_fingerprint(cfg))  # no error
        # --resume and --overwrite exclude each other, and so do repo_ids and dataset_paths (__post_init__)
        if key not in ("overwrite", "stream.repo_ids"):
            everything = with_leaf(everything, path, new)
    cfg = _parse(everything, tmp_path, out)
    assert cfg.wake.num_workers == 1 and cfg.eval.videos_per_skill == 0 and cfg.progress
    check_resume(cfg, resume_fingerprint(cfg))


def test_a_run_made_on_another_device_is_refused(stored, tmp_path):
    out, saved = stored
    run = tmp_path / "run"
    shutil.copytree(out, run)
    settings = {**read_fingerprint(run / FINGERPRINT_FILE), "policy.device": "cuda"}  # as a GPU run stores it
    write_fingerprint(run / FINGERPRINT_FILE, SettingsFingerprint(settings, settings_digest(settings)))
    cfg = _parse(saved, tmp_path, run)
    err = assert_refused_naming(lambda: check_resume(cfg, resume_fingerprint(cfg)),
                                "policy.device")
    assert 'policy.device: "cuda" -> "cpu"' in str(err)


def test_refused_resumes_leave_the_run_byte_identical_and_a_plain_resume_still_works(
        after_stage_1, reference, tmp_path, fake_env_cli):
    """End to end through ``sr-train``: the module docstring's settings, each refused before anything is written
    (files, bytes and modification times unchanged); then the plain resume finishes the run exactly like an
    uninterrupted one."""
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    resume = [f"--config_path={run / 'train_config.json'}", "--resume=true"]
    before = tree_state(run)
    for flag, key, change in [
        ("--sleep.batch_size=8", "sleep.batch_size", "4 -> 8"),
        ("--policy.n_action_steps=2", "policy.n_action_steps", "4 -> 2"),
        ("--sleep.anchor_tau=0.5", "sleep.anchor_tau", "null -> 0.5"),
        ("--policy.dim_feedforward=128", "policy.dim_feedforward", "64 -> 128"),
    ]:
        err = assert_refused_naming(lambda f=flag: cli.train_main([*resume, f]), key)
        assert f"{key}: {change}" in str(err) and len(err.diffs) == 1
        assert tree_state(run) == before, flag
    err = assert_refused_naming(lambda: cli.train_main([*resume, "--policy.optimizer_lr=0.001", "--seed=8"]), "seed")
    assert set(err.diffs) == {"policy.optimizer_lr", "seed"} and tree_state(run) == before
    stored_files = {name: (run / name).read_bytes() for name in ("train_config.json", FINGERPRINT_FILE)}
    cli.train_main(resume)
    assert {name: (run / name).read_bytes() for name in stored_files} == stored_files  # never rewritten
    ref_out, ref_results = reference
    assert json.loads((run / "results.json").read_text())["metrics"] == ref_results["metrics"]
    final, ref = _weights(run), _weights(ref_out)
    assert all(torch.equal(final[k], ref[k]) for k in ref)


def test_a_copied_run_resumes_where_it_is_with_allow_listed_changes(after_stage_1, reference, tmp_path, fake_env_cli):
    """A run directory copied elsewhere resumes in the copy (its train_config.json stores output_dir "."), never
    touching the original; allow-listed settings changed on the way (DataLoader workers, videos, progress bars)
    leave the weights bit-identical to an uninterrupted run."""
    original = after_stage_1
    copy = tmp_path / "elsewhere" / "run"
    shutil.copytree(original, copy)
    original_state = tree_state(original)
    cli.train_main([f"--config_path={copy / 'train_config.json'}", "--resume=true", "--wake.num_workers=1",
                    "--eval.videos_per_skill=0", "--eval.video_height=64", "--progress=true"])
    assert tree_state(original) == original_state
    progress = json.loads((copy / "progress.json").read_text())["completed"]
    assert {"2.wake", "2.memory", "2.wake.eval", "2.sleep", "2.sleep.eval"} <= set(progress)
    assert (copy / "results.json").is_file() and not (original / "results.json").exists()
    # results show the settings the run started with, not the resumed invocation's (videos were 1, resumed with 0)
    assert json.loads((copy / "results.json").read_text())["config"]["eval"]["videos_per_skill"] == 1
    ref_out, ref_results = reference
    assert json.loads((copy / "results.json").read_text())["metrics"] == ref_results["metrics"]
    for phase in ("skill_2_place/wake", "skill_2_place/sleep"):
        final, ref = _weights(copy, phase), _weights(ref_out, phase)
        assert all(torch.equal(final[k], ref[k]) for k in ref), phase
    for path in copy.rglob("*.json"):  # nothing in the run directory names where it (or its original) is
        text = path.read_text()
        assert str(original) not in text and str(copy) not in text, path


def test_a_run_without_fingerprint_is_refused_naming_the_file(stored, tmp_path):
    """The fingerprint is the first file a run writes: a run directory without it is never resumed, and its settings
    are never re-created from train_config.json (not sealed: an edited copy would become the run's settings)."""
    out, saved = stored
    run = tmp_path / "old"
    shutil.copytree(out, run)
    (run / FINGERPRINT_FILE).unlink()
    before = tree_state(run)
    with pytest.raises(CorruptFileError, match=f"{FINGERPRINT_FILE}: missing: cannot resume"):
        ACTTrainer(_parse(saved, tmp_path, run)).run_dir.prepare()
    assert tree_state(run) == before and not (run / FINGERPRINT_FILE).exists()
    (run / "train_config.json").unlink()
    with pytest.raises(FileNotFoundError, match="holds no run to resume"):
        ACTTrainer(_parse(saved, tmp_path, run)).run_dir.prepare()


def test_a_start_killed_while_writing_train_config_gets_it_on_resume(stored, state_datasets, tmp_path):
    """A kill inside the atomic write of train_config.json leaves the fingerprint and a torn temporary file: the
    resume (the same command with --resume=true; its settings match the fingerprint) writes the config an
    uninterrupted start writes, byte for byte. Before: the run resumed to its end without one, and results.json took
    its config from the resuming invocation."""
    out, _ = stored
    run = tmp_path / "killed"
    shutil.copytree(out, run)
    (run / "train_config.json").unlink()
    (run / ".train_config.json.k2.tmp").write_bytes((out / "train_config.json").read_bytes()[:100])
    cfg = tiny_stream_config(state_datasets, run, STREAM, use_images=False)
    cfg.resume = True
    ACTTrainer(cfg).run_dir.prepare()
    assert sorted(p.name for p in run.iterdir()) == [FINGERPRINT_FILE, "train_config.json"]
    assert (run / "train_config.json").read_bytes() == (out / "train_config.json").read_bytes()


@pytest.mark.parametrize("damage", ["flip", "truncate", "config"])
def test_a_damaged_checkpoint_is_refused_naming_the_file_before_training_on_it(after_stage_1, state_datasets, tmp_path,
                                                                               damage):
    """Stage 2 starts from stage 1's checkpoint: one flipped weight byte, a truncated model.safetensors or an edited
    config.json in it is refused naming the file (before: a different result with no error, or an unnamed
    SafetensorError)."""
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    pretrained = run / "skill_1_approach" / "wake" / "pretrained_model"
    target = pretrained / ("config.json" if damage == "config" else "model.safetensors")
    data = bytearray(target.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) - 5] ^= 0x01
    target.write_bytes(bytes(data))
    cfg = tiny_stream_config(state_datasets, run, STREAM, use_images=False)
    cfg.resume = True
    with pytest.raises(CorruptFileError, match=f"{target.name}: contents differ from checksums.json"):
        ACTTrainer(cfg, fake_env_factory).run()


def test_extending_a_finished_one_skill_run_equals_the_two_skill_run(state_datasets, reference, tmp_path):
    """--stream.extend_from: stage 1 (no sleep, so the final-skill rule cannot matter) is imported, not re-run, and
    the extended stream ends bit-identical to the stream that had both skills from the start."""
    source = tmp_path / "one_skill"
    train_stream(tiny_stream_config(state_datasets, source, STREAM[:1], use_images=False), fake_env_factory)
    cfg = tiny_stream_config(state_datasets, tmp_path / "extended", STREAM, use_images=False)
    cfg.stream.extend_from = source
    ran = []
    extended = ACTTrainer(cfg, fake_env_factory, after_phase=lambda k, p: ran.append((k, p))).run()
    assert {k for k, _ in ran} == {1}
    ref_out, ref_results = reference
    assert extended["metrics"] == ref_results["metrics"]
    final, ref = _weights(tmp_path / "extended"), _weights(ref_out)
    assert all(torch.equal(final[k], ref[k]) for k in ref)
    other = tiny_stream_config(state_datasets, tmp_path / "refused", STREAM, use_images=False)
    other.stream.extend_from, other.sleep.lr = source, 0.5
    with pytest.raises(SettingsMismatchError, match="sleep.lr"):
        ACTTrainer(other, fake_env_factory).run()
    assert not (tmp_path / "refused").exists()


def _one_line_refusal(argv: list[str], capsys) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        run_cli("sr-train", cli.train_main, argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and err.startswith("sr-train: error: "), err
    return err


def test_an_edited_or_damaged_train_config_is_refused_naming_it_before_anything_is_written(
        after_stage_1, state_datasets, tmp_path, fake_env_cli, capsys):
    """Before: the sleep lr edited in train_config.json (valid JSON) resumed with the fingerprint's lr but
    results.json recorded the edited one; one flipped byte redid stage 3, then failed with "Expecting ','
    delimiter" without naming the file, at every further resume."""
    for damage in ("edit", "flip", "unseal-edit"):
        run = tmp_path / damage / "run"
        shutil.copytree(after_stage_1, run)
        path = run / "train_config.json"
        text = path.read_text()
        data = json.loads(text)
        if damage == "flip":  # invalid JSON
            at = text.index('"sleep"')
            path.write_text(text[:at] + "'" + text[at + 1:])
        else:  # valid JSON with another lr; "unseal-edit": the seal removed too, as a file of before seals
            data["sleep"]["lr"] = data["sleep"]["lr"] * 2
            if damage == "unseal-edit":
                del data["sha256"]
            path.write_text(json.dumps(data, indent=2, sort_keys=True))
        before = tree_state(run)
        cfg = tiny_stream_config(state_datasets, run, STREAM, use_images=False)
        cfg.resume = True
        with pytest.raises(CorruptFileError, match=re.escape(str(path))):
            train_stream(cfg, fake_env_factory)
        assert tree_state(run) == before, damage
        err = _one_line_refusal([f"--config_path={path}", "--resume=true"], capsys)
        assert str(path) in err or (damage == "unseal-edit" and "sleep.lr" in err), (damage, err)
        assert tree_state(run) == before, damage


def test_a_train_config_written_before_seals_resumes_when_it_holds_the_run_settings(after_stage_1, reference, tmp_path,
                                                                                    fake_env_cli):
    run = tmp_path / "run"
    shutil.copytree(after_stage_1, run)
    path = run / "train_config.json"
    path.write_text(json.dumps(read_config_json(path)[0], indent=2, sort_keys=True))  # as older runs wrote it
    cli.train_main([f"--config_path={path}", "--resume=true"])
    assert json.loads((run / "results.json").read_text())["metrics"] == reference[1]["metrics"]
