"""The base-learner probe: one skill's wake from scratch under the chosen normalization statistics, evaluated right
after; finished probes are skipped; the table names every probe."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import skill_probe
from experiments.skill_probe import ProbeConfig, final_errors, run
from sr_imitation.substrates.act.data import load_stats
from sr_imitation.substrates.act.trainer import stored_config_dict
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config


def test_probe_uses_the_chosen_statistics_and_skips_finished_probes(state_datasets, tmp_path, monkeypatch):
    train = stored_config_dict(tiny_stream_config(state_datasets, tmp_path / "unused", SKILLS, use_images=False))
    preset = tmp_path / "preset.json"
    preset.write_text(json.dumps({"record": {"root": str(state_datasets), "num_episodes": 3}, "train": train}))
    cfg = ProbeConfig(preset=preset, skills=["insert"], stats=["own", "first", "union"], seeds=[0],
                      output_root=tmp_path / "probe")
    results = run(cfg, fake_env_factory)
    assert [(r["skill"], r["stats"]) for r in results] == [("insert", s) for s in ("own", "first", "union")]
    assert all(r["wake_steps"] == 4 and len(r["success_per_seed"]) == 2 for r in results)
    means = {s: load_stats(tmp_path / "probe" / f"insert_{s}_seed0" / "stream_stats.safetensors")
             ["observation.state"]["mean"] for s in ("own", "first", "union")}
    meta = {s: json.loads((state_datasets / s / "meta" / "stats.json").read_text())["observation.state"]["mean"]
            for s in SKILLS}
    np.testing.assert_allclose(means["own"], meta["insert"], atol=1e-5)  # the skill's own dataset
    np.testing.assert_allclose(means["first"], meta["approach"], atol=1e-5)  # the preset stream's first skill's
    np.testing.assert_allclose(means["union"], np.mean([meta[s] for s in SKILLS], axis=0), atol=1e-4)  # equal sizes
    table = (tmp_path / "probe" / "probe.md").read_text()
    assert table.count("| insert |") == 3 + 3  # success table and feature-RMS table
    assert all(set(r["feature_rms"]) == {"robot_state", "env_state", "encoder"} for r in results)
    assert all(0 < v < 1e3 for r in results for v in r["feature_rms"].values())
    monkeypatch.setattr(skill_probe.ProbeSubstrate, "setup", lambda self: pytest.fail("a finished probe re-ran"))
    assert run(cfg, fake_env_factory) == results
    with pytest.raises(ValueError, match="not in the preset's stream"):
        run(ProbeConfig(preset=preset, skills=["pullout"], output_root=tmp_path / "p2"), fake_env_factory)


@pytest.mark.parametrize("norm", ["group", "frozen_batch"])
def test_probe_measures_the_camera_features_it_is_asked_about(image_datasets, tmp_path, norm):
    """The vision probe reports the backbone's feature scale (how the unnormalized random ResNet was found)."""
    train = stored_config_dict(tiny_stream_config(image_datasets, tmp_path / "unused", SKILLS, backbone_norm=norm))
    preset = tmp_path / "preset.json"
    preset.write_text(json.dumps({"record": {"root": str(image_datasets), "num_episodes": 3}, "train": train}))
    (result,) = run(ProbeConfig(preset=preset, skills=["approach"], stats=["own"], seeds=[0],
                                output_root=tmp_path / "probe"), fake_env_factory)
    assert set(result["feature_rms"]) == {"robot_state", "camera0", "encoder"}
    assert "camera0" in (tmp_path / "probe" / "probe.md").read_text()


def test_final_errors_of_a_needle_state():
    state = np.zeros(35, np.float32)
    state[7:10] = [0.3, 0.0, 0.4]  # goal 5 mm away (cm units)
    state[7 + 5] = np.radians(20.0)  # goal yaw 20 degrees off
    state[6] = 0.05
    errors = final_errors(state)
    assert errors["position_mm"] == pytest.approx(5.0) and errors["rotation_deg"] == pytest.approx(20.0, abs=1e-3)
    assert errors["jaw"] == pytest.approx(0.05) and final_errors(np.zeros(6)) == {}
