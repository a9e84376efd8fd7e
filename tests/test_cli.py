"""``sr-train``: one command for both substrates, with the same flag names for shared concepts."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from lerobot_policy_act_sr import ACTSRConfig
from sr_imitation import cli
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.infra.fingerprint import settings_fingerprint
from sr_imitation.stream.config import POLICY_ALIASES, RENAMED_FLAGS, renamed_flag_hint, renamed_key_hint
from sr_imitation.substrates import discover
from sr_imitation.substrates.act.trainer import RESUME_ALLOW_LIST, TrainStreamConfig, stored_config_dict
from sr_imitation.substrates.sac.config import RLTrainConfig
from tests.test_cli_errors import _one_line_error

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SHARED = {"substrate", "method", "stream", "wake", "memory", "sleep", "eval", "seed", "output_dir", "resume",
          "overwrite", "progress", "wandb"}


def _fields(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def test_both_substrates_share_the_flag_names_of_shared_concepts():
    act, sac = _fields(TrainStreamConfig), _fields(RLTrainConfig)
    assert set(act) >= SHARED and set(sac) >= SHARED
    act_cfg, sac_cfg = TrainStreamConfig(), RLTrainConfig()
    assert isinstance(act_cfg.sleep, SleepConfig) and isinstance(sac_cfg.sleep, SleepConfig)
    assert act_cfg.sleep.enabled and sac_cfg.sleep.enabled
    for name in ("skills", "extend_from"):
        assert hasattr(act_cfg.stream, name) and hasattr(sac_cfg.stream, name)
    for name in ("episodes", "videos_per_skill", "video_height", "video_width"):
        assert hasattr(act_cfg.eval, name) and hasattr(sac_cfg.eval, name)
    assert hasattr(act_cfg.memory, "buffer_size") and hasattr(sac_cfg.memory, "buffer_size")
    # the paper's two sleep tables as the two substrates' defaults
    assert (act_cfg.sleep.lr, act_cfg.sleep.anchor_tau, act_cfg.sleep.max_iterations) == (1e-5, None, 1000)
    assert (sac_cfg.sleep.lr, sac_cfg.sleep.anchor_tau, sac_cfg.sleep.max_iterations) == (5e-4, 150.0, 4000)


@pytest.mark.parametrize("args, substrate", [
    ([], "act"),
    (["--substrate=sac"], "sac"),
    ([f"--config_path={CONFIGS / 'sac_mt5_cpu.json'}"], "sac"),
    ([f"--config_path={CONFIGS / 'sac_mt5_paper.json'}"], "sac"),
    ([f"--config_path={CONFIGS / 'needle_cpu.json'}"], "act"),
    ([f"--config_path={CONFIGS / 'needle_paper.json'}"], "act"),
])
def test_the_substrate_comes_from_the_flag_or_the_config_file(args, substrate):
    assert cli.substrate_of(args) == substrate


@pytest.mark.parametrize("name", sorted(p.name for p in CONFIGS.glob("*.json")))
def test_every_preset_parses_with_sr_train_and_takes_shared_flags(name):
    """Every preset in configs/ runs with the command configs/README.md names (``sr-train --config_path=...``),
    and the shared flags mean the same thing on it."""
    cfg = cli.parse_args([f"--config_path={CONFIGS / name}", "--seed=5", "--sleep.enabled=false",
                          "--sleep.anchor_strength=0.5", "--eval.episodes=3", "--method=sr"])
    assert cfg.substrate == json.loads((CONFIGS / name).read_text()).get("substrate", "act")
    assert (cfg.seed, cfg.sleep.enabled, cfg.sleep.anchor_strength, cfg.eval.episodes) == (5, False, 0.5, 3)
    assert "sr-train" in (CONFIGS / "README.md").read_text()


def test_a_run_s_stored_config_resumes_through_sr_train(tmp_path):
    """A run's config file names its substrate, so ``sr-train --config_path=<run>/config.json`` needs no flag."""
    cfg = cli.parse_args([f"--config_path={CONFIGS / 'sac_mt5_cpu.json'}", f"--output_dir={tmp_path / 'run'}"])
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text(json.dumps(cfg.stored_config()))
    again = cli.parse_args([f"--config_path={tmp_path / 'run' / 'config.json'}"])
    assert isinstance(again, RLTrainConfig) and again.output_dir == tmp_path / "run"


@pytest.mark.parametrize("old", sorted(RENAMED_FLAGS))
def test_a_flag_of_an_earlier_version_is_one_line_naming_its_new_name(old, tmp_path, capsys):
    out = tmp_path / "run"
    line = _one_line_error("sr-train", cli.train_main, [f"--output_dir={out}", f"{old}=1"], capsys)
    assert RENAMED_FLAGS[old] in line and old in line and not out.exists()


def test_a_config_file_of_an_earlier_version_is_one_line_naming_the_key(tmp_path, capsys):
    preset = json.loads((CONFIGS / "needle_cpu.json").read_text())
    preset["train"]["policy"]["sleep_lr"] = 1e-4
    path = tmp_path / "old.json"
    path.write_text(json.dumps(preset))
    line = _one_line_error("sr-train", cli.train_main, [f"--config_path={path}"], capsys)
    assert str(path) in line and "'policy.sleep_lr' was renamed: use 'sleep.lr'" in line
    rl = json.loads((CONFIGS / "sac_mt5_cpu.json").read_text())
    rl["sleep_enabled"] = False
    path.write_text(json.dumps(rl))
    line = _one_line_error("sr-train", cli.train_main, [f"--config_path={path}"], capsys)
    assert "'sleep_enabled' was renamed: use 'sleep.enabled'" in line


def test_an_unknown_substrate_and_a_mismatched_config_are_one_line(tmp_path, capsys):
    line = _one_line_error("sr-train", cli.train_main, ["--substrate=diffusion"], capsys)
    assert f"substrate: unknown substrate 'diffusion'; choose from {sorted(discover())}" in line  # the registry's
    line = _one_line_error("sr-train", cli.train_main, [f"--config_path={CONFIGS / 'sac_mt5_cpu.json'}",
                                                        f"--output_dir={tmp_path / 'r'}", "--sleep.seed=4"], capsys)
    assert "sleep.seed" in line and not (tmp_path / "r").exists()


@pytest.mark.parametrize("args, shows, hides", [
    (["--help"], ["--sleep.enabled", "--memory.buffer_size", "--stream.skills", "--policy.distill_weight_later",
                  "Adam learning rate eta_sleep (SurgicAI table"],
     ["diffusion", "--sac.actor_lr"]),
    (["--substrate=sac", "--help"], ["--sleep.enabled", "--memory.buffer_size", "--stream.name", "--sac.actor_lr",
                                     "Adam learning rate eta_sleep (MT5 5e-4"],
     ["--policy.", "diffusion"]),
])
def test_help_shows_the_substrate_s_flags_only(args, shows, hides, capsys):
    with pytest.raises(SystemExit) as info:
        cli.train_main(args)
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert all(s in out for s in shows), [s for s in shows if s not in out]
    assert not any(h in out for h in hides), [h for h in hides if h in out]


# --policy.sleep (the design card's name) is --sleep.enabled on sr-train: one setting. --------------------------------

@pytest.mark.parametrize("args, enabled, buffer_size", [
    (["--policy.sleep=true"], True, 1024),
    (["--policy.sleep=false"], False, 1024),
    (["--policy.sleep", "false"], False, 1024),
    (["--policy.type=act_sr", "--policy.sleep=false", "--policy.dim_model=64"], False, 1024),
    (["--policy.sleep=false", "--sleep.enabled=false"], False, 1024),  # both, agreeing
    (["--policy.sleep=null"], True, 1024),  # not given
    (["--policy.sleep_memory_size=16"], True, 16),  # likewise --memory.buffer_size
    (["--substrate=sac", "--policy.sleep=false"], False, 1000),  # SAC has no policy section: the same mapping
    (["--substrate=sac", "--policy.sleep=true"], True, 1000),
])
def test_policy_sleep_is_the_sleep_switch(args, enabled, buffer_size):
    cfg = cli.parse_args(args)
    assert (cfg.sleep.enabled, cfg.memory.buffer_size) == (enabled, buffer_size)
    if isinstance(cfg, TrainStreamConfig):  # the parsed and stored config hold one value: sleep.enabled
        assert cfg.policy.sleep is None and cfg.policy.sleep_memory_size is None
        assert stored_config_dict(cfg)["policy"]["sleep"] is None


def test_policy_sleep_overrides_a_config_file_like_any_flag(tmp_path):
    preset = json.loads((CONFIGS / "needle_cpu.json").read_text())
    preset["train"]["sleep"]["enabled"] = False
    path = tmp_path / "off.json"
    path.write_text(json.dumps(preset))
    assert not cli.parse_args([f"--config_path={path}"]).sleep.enabled
    assert cli.parse_args([f"--config_path={path}", "--policy.sleep=true"]).sleep.enabled
    assert not cli.parse_args([f"--config_path={CONFIGS / 'needle_cpu.json'}", "--policy.sleep=false"]).sleep.enabled
    # a file may use the policy's name too: folded the same way, and the command line still overrides it
    run = {"policy": {"type": "act_sr", "sleep": False}, "output_dir": str(tmp_path / "run")}
    path.write_text(json.dumps(run))
    cfg = cli.parse_args([f"--config_path={path}"])
    assert not cfg.sleep.enabled and cfg.policy.sleep is None
    assert cli.parse_args([f"--config_path={path}", "--sleep.enabled=true"]).sleep.enabled
    assert cli.parse_args([f"--config_path={path}", "--policy.sleep=true"]).sleep.enabled


def _write(tmp_path: Path, tree: dict) -> str:
    path = tmp_path / "both.json"
    path.write_text(json.dumps(tree))
    return f"--config_path={path}"


@pytest.mark.parametrize("args, names", [
    (["--policy.sleep=true", "--sleep.enabled=false"], ["--policy.sleep=true", "--sleep.enabled=false"]),
    (["--sleep.enabled=true", "--policy.sleep=false"], ["--policy.sleep=false", "--sleep.enabled=true"]),
    ([f"--config_path={CONFIGS / 'needle_cpu.json'}", "--policy.sleep=false", "--sleep.enabled=true"],
     ["--policy.sleep=false", "--sleep.enabled=true"]),
    (["--policy.sleep_memory_size=16", "--memory.buffer_size=32"],
     ["--policy.sleep_memory_size=16", "--memory.buffer_size=32"]),
    (["--substrate=sac", "--policy.sleep=true", "--sleep.enabled=false"], ["--policy.sleep", "--sleep.enabled"]),
    ([{"policy": {"type": "act_sr", "sleep": False}, "sleep": {"enabled": True}}],
     ["policy.sleep=false", "sleep.enabled=true", "both.json"]),
    (["--policy.sleep=maybe"], ["--policy.sleep", "true or false", "maybe"]),
    (["--policy.sleep"], ["--policy.sleep", "true or false"]),
])
def test_policy_sleep_and_sleep_enabled_that_disagree_are_one_line_naming_both(args, names, tmp_path, capsys):
    args = [_write(tmp_path, a) if isinstance(a, dict) else a for a in args]
    out = tmp_path / "run"
    line = _one_line_error("sr-train", cli.train_main, [*args, f"--output_dir={out}"], capsys)
    assert all(n in line for n in names), line
    assert "renamed" not in line and not out.exists()


def test_policy_sleep_is_no_longer_answered_as_a_renamed_flag():
    assert "--policy.sleep" not in RENAMED_FLAGS and "--policy.sleep_memory_size" not in RENAMED_FLAGS
    assert renamed_flag_hint(["--policy.sleep=true"]) is None
    assert renamed_key_hint({"policy": {"sleep": True}}) is None
    assert set(POLICY_ALIASES) == {"policy.sleep", "policy.sleep_memory_size"}


def test_a_config_built_in_python_folds_policy_sleep_or_refuses_a_disagreement():
    cfg = TrainStreamConfig(policy=ACTSRConfig(device="cpu", sleep=True, sleep_memory_size=1024))
    assert cfg.sleep.enabled and cfg.policy.sleep is None and cfg.policy.sleep_memory_size is None
    with pytest.raises(ValueError, match=r"policy\.sleep=false and sleep\.enabled=true disagree"):
        TrainStreamConfig(policy=ACTSRConfig(device="cpu", sleep=False))


def test_runs_made_before_policy_sleep_existed_keep_their_fingerprint(tmp_path):
    """A run's settings_fingerprint.json from before these settings existed has no policy.sleep keys: they are
    allow-listed (always null once folded), so the fingerprint of the same settings is unchanged and it resumes."""
    cfg = cli.parse_args([f"--config_path={CONFIGS / 'needle_cpu.json'}", f"--output_dir={tmp_path / 'run'}"])
    tree = stored_config_dict(cfg)
    old = json.loads(json.dumps(tree))
    del old["policy"]["sleep"], old["policy"]["sleep_memory_size"]
    new_fp, old_fp = (settings_fingerprint(t, RESUME_ALLOW_LIST) for t in (tree, old))
    assert new_fp.sha256 == old_fp.sha256 and not any(k.startswith("policy.sleep") for k in new_fp.settings)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "train_config.json").write_text(json.dumps(old))  # an older run's stored config
    again = cli.parse_args([f"--config_path={tmp_path / 'run' / 'train_config.json'}"])
    assert again.policy.sleep is None and again.sleep.enabled == cfg.sleep.enabled
    assert settings_fingerprint(stored_config_dict(again), RESUME_ALLOW_LIST).sha256 == old_fp.sha256
