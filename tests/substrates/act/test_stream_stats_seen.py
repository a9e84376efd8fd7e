"""``--stream.stats=seen``, the default: the statistics of the skills seen so far, updated at each wake, saved with
the run, the policy and the memories' targets re-expressed when they change; a resume computes the same numbers.
A skill whose data lies far outside the statistics in use is reported before its first gradient; methods that keep
normalized data of earlier skills are refused with seen (they give first or union)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.substrates.act.config import StreamConfig
from sr_imitation.substrates.act.data import load_metadata, load_stats, stream_stats
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.offline_sleep import load_policy
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.substrates.act.helpers import make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place", "insert"]


class StopError(Exception):
    pass


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("seen")
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i, image=False, offset=3.0 * i)
    return root


def _config(root: Path, out: Path, skills=SKILLS, **kwargs):
    cfg = tiny_stream_config(root, out, skills, use_images=False, stats=kwargs.pop("stats", "seen"), **kwargs)
    cfg.eval = EvalConfig(env="none", episodes=0)
    return cfg


def test_seen_is_the_default_and_first_and_union_stay_choices():
    assert StreamConfig().stats == "seen"
    for choice in ("first", "union"):
        assert StreamConfig(stats=choice).stats == choice
    with pytest.raises(ValueError, match="stream.stats must be one of"):
        StreamConfig(stats="all")


def test_each_stage_normalizes_with_the_skills_seen_so_far_and_a_resume_gives_the_same_numbers(datasets, tmp_path):
    whole = tmp_path / "whole"
    results = ACTTrainer(_config(datasets, whole)).run()
    metas = [load_metadata(datasets / s, f"local/sr_needle_{s}") for s in SKILLS]
    first = load_stats(whole / "stream_stats.safetensors")
    for k in (1, 2):
        saved = load_stats(whole / f"skill_{k + 1}_{SKILLS[k]}" / "stream_stats.safetensors")
        expected = stream_stats(metas[: k + 1], {"observation.state": None, "observation.environment_state": None})
        assert torch.allclose(saved["observation.state"]["mean"], expected["observation.state"]["mean"])
        assert not torch.equal(saved["action"]["mean"], first["action"]["mean"])
        # the stage's checkpoints are saved with its statistics
        policy = load_policy(whole / f"skill_{k + 1}_{SKILLS[k]}" / "sleep" / "pretrained_model", "cpu")
        assert torch.allclose(policy.stats["action"]["mean"], saved["action"]["mean"])
    # the earlier skills' memories are compared in the statistics in use: finite, of the order of the wake's losses
    losses = results["losses"]["memory_loss"][-1]
    assert all(x is not None and 0 <= x < 10 for x in losses), losses
    # killed after the third skill's wake, resumed: the same weights and losses
    cut = tmp_path / "cut"

    def stop(k: int, phase: str) -> None:
        if (k, phase) == (2, "wake"):
            raise StopError

    with pytest.raises(StopError):
        ACTTrainer(_config(datasets, cut), after_phase=stop).run()
    cfg = _config(datasets, cut)
    cfg.resume = True
    resumed = ACTTrainer(cfg).run()
    for phase in ("skill_3_insert/wake", "skill_3_insert/sleep"):
        a, b = (load_file(str(r / phase / "pretrained_model" / "model.safetensors")) for r in (whole, cut))
        assert all(torch.equal(a[n], b[n]) for n in a), phase
    assert resumed["losses"] == results["losses"]


def test_a_skill_far_outside_the_statistics_in_use_is_reported_before_its_first_gradient(tmp_path, caplog):
    root = tmp_path / "far"
    make_skill_dataset(root, "approach", 0, image=False, offset=0.0)
    make_skill_dataset(root, "place", 1, image=False, offset=40.0)
    with caplog.at_level(logging.WARNING, logger="sr_imitation.substrates.act.substrate"):
        ACTTrainer(_config(root, tmp_path / "first", ["approach", "place"], stats="first")).run()
    lines = [r.getMessage() for r in caplog.records if "standard deviations from the mean" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith("skill place: its observation.state[")
    assert "(--stream.stats=first)" in lines[0] and "--stream.stats=seen" in lines[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sr_imitation.substrates.act.substrate"):
        ACTTrainer(_config(root, tmp_path / "seen", ["approach", "place"])).run()
    assert not [r for r in caplog.records if "standard deviations from the mean" in r.getMessage()]
    # under seen the statistics in use hold place already: the line says how far it lies outside approach's
    lines = [r.getMessage() for r in caplog.records if "outside the statistics of the skills before" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith("skill place: its ") and "--stream.stats=union" in lines[0]
    z = float(lines[0].split(" lies ")[1].split(" standard")[0])
    assert z > 10


def test_seen_says_nothing_of_a_skill_inside_the_statistics_before_it(tmp_path, caplog):
    root = tmp_path / "near"
    make_skill_dataset(root, "approach", 0, image=False, offset=0.0)
    make_skill_dataset(root, "place", 1, image=False, offset=0.0)
    with caplog.at_level(logging.WARNING, logger="sr_imitation.substrates.act.substrate"):
        ACTTrainer(_config(root, tmp_path / "seen", ["approach", "place"])).run()
    assert not [r for r in caplog.records if "standard deviations" in r.getMessage()]


def test_methods_that_keep_normalized_data_are_refused_with_seen(datasets, tmp_path):
    cfg = _config(datasets, tmp_path / "replay")
    cfg.method = "replay"
    with pytest.raises(ValueError, match=r"^stream.stats=seen \(the default\) re-expresses .* method 'replay'"):
        ACTSubstrate(cfg)
    cfg.stream.stats = "first"
    ACTSubstrate(cfg)


def test_archived_runs_and_presets_keep_their_recorded_setting(tmp_path):
    import json

    from sr_imitation.substrates.act.cli import parse_train_config
    from sr_imitation.substrates.act.config import stored_config_dict
    from sr_imitation.substrates.act.trainer import SETTINGS_ADDED

    root = Path(__file__).resolve().parents[3]
    # a run written before the setting existed normalized with the first skill's statistics: its config is read so
    stored = stored_config_dict(_config(tmp_path, tmp_path / "old", stats="first"))
    del stored["stream"]["stats"]
    archived = tmp_path / "old" / "train_config.json"
    archived.parent.mkdir()
    archived.write_text(json.dumps(stored))
    assert parse_train_config(str(archived), []).stream.stats == "first"
    assert parse_train_config(str(archived), ["--stream.stats=seen"]).stream.stats == "seen"
    assert SETTINGS_ADDED["stream.stats"] == "first"  # its fingerprint, without the key, resumes with first
    # every ACT preset states its statistics
    for preset in ("needle_cpu", "needle_cpu_m16", "needle_cpu_vision", "needle_paper", "needle_try"):
        assert parse_train_config(str(root / "configs" / f"{preset}.json"), []).stream.stats == "union", preset


def test_reexpress_inputs_false_rewrites_the_action_head_only(datasets, tmp_path):
    """``--stream.reexpress_inputs=false`` (exploratory): under seen the state input weights keep the scale
    training leaves them at, while the action head is still re-expressed (a memory's targets stay finite), and the
    setting is refused where the statistics never change."""
    from sr_imitation.reporting.input_scale import STATE_INPUT, stage_input_norms
    from sr_imitation.substrates.act.normalization import reexpress_state_dict

    cfg = _config(datasets, tmp_path / "actions")
    cfg.stream.reexpress_inputs = False
    results = ACTTrainer(cfg).run()
    norms = stage_input_norms(cfg.output_dir)
    assert max(r["max"] for r in norms) < 2 * norms[0]["max"]
    assert all(x is not None and 0 <= x < 10 for x in results["losses"]["memory_loss"][-1])
    metas = [load_metadata(datasets / s, f"local/sr_needle_{s}") for s in SKILLS]
    old, new = (stream_stats(m, {"observation.state": None}) for m in (metas[:1], metas))
    state = load_file(str(cfg.output_dir / "skill_1_approach" / "wake" / "pretrained_model" / "model.safetensors"))
    head = reexpress_state_dict(state, old, new, inputs=False)
    assert torch.equal(head[STATE_INPUT], state[STATE_INPUT])
    assert not torch.equal(head["model.action_head.weight"], state["model.action_head.weight"])
    assert not torch.equal(reexpress_state_dict(state, old, new)[STATE_INPUT], state[STATE_INPUT])
    with pytest.raises(ValueError, match="reexpress_inputs=false acts only when the statistics change"):
        StreamConfig(stats="union", reexpress_inputs=False)
