"""``sr-train``: one command for both substrates, with the same flag names for shared concepts (issue 10)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from sr_imitation import cli
from sr_imitation.core.sleep import SleepConfig
from sr_imitation.imitation.stream import TrainStreamConfig
from sr_imitation.rl.config import RLTrainConfig
from sr_imitation.stream.config import RENAMED_FLAGS
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
    assert "substrate" in line and "'act', 'sac'" in line
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
