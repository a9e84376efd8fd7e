"""The wake-sleep stream trainer on tiny synthetic datasets: outputs, stats policy, resume, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.core.memory import load_memory
from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.io import CorruptFileError, write_checked_json
from sr_imitation.stream import StreamEngine
from sr_imitation.substrates.act.data import DatasetMismatchError
from sr_imitation.substrates.act.trainer import StreamConfig, train_stream
from sr_imitation.substrates.act.wake import NonFiniteLossError
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, make_skill_dataset, tiny_stream_config


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_file(str(path / "pretrained_model" / "model.safetensors"))


@pytest.fixture(scope="module")
def finished_run(state_datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "stream"
    results = train_stream(tiny_stream_config(state_datasets, out, SKILLS, use_images=False), fake_env_factory)
    return out, results


def test_a_stream_writes_every_stage_memory_and_report(finished_run):
    out, results = finished_run
    for k, skill in enumerate(SKILLS, start=1):
        stage = out / f"skill_{k}_{skill}"
        assert (stage / "wake" / "pretrained_model" / "config.json").is_file()
        assert (stage / "wake" / "eval.json").is_file() and (stage / "wake" / "trajectories.safetensors").is_file()
        assert (stage / "sleep").is_dir() == (k >= 2)
        memory = load_memory(out / "memories" / f"skill_{k}_{skill}.safetensors", skill=skill)
        assert memory.size == 16 and memory.config["snapshot"] == f"skill_{k}_{skill}/wake"
    for name in ("results.json", "results.md", "metrics.png", "success_matrix.png", "progress.json"):
        assert (out / name).is_file(), name
    s = results["success_matrix"]
    assert len(s) == 3 and s[0][1] is None and all(0.0 <= x <= 1.0 for x in s[2])
    assert set(results["metrics"]) == {"afsr", "prs", "bwt", "bwt_wake", "spi"}
    assert results["metrics"]["prs"]["curve"][0] is None  # PRS only for k >= 2
    assert (results["substrate"], results["label"], results["eval_units"]) == ("act", "sr", 2)
    sleeps = {f"{st['stage'] + 1}.sleep": st["sleep"] for st in results["stages"] if "sleep" in st}
    assert set(sleeps) == {"2.sleep", "3.sleep"}
    sleep_cfg = tiny_stream_config(Path("unused"), out, SKILLS).sleep
    # N_sleep = 3 < 2 windows of 2: the plateau rule cannot fire, every sleep runs its whole budget.
    assert sleep_cfg.max_iterations == 3 and sleep_cfg.early_stop_window == 2
    for k in (2, 3):
        record, name = sleeps[f"{k}.sleep"], f"skill_{k}_{SKILLS[k - 1]}"
        diag = json.loads((out / name / "sleep" / "sleep_diagnostics.json").read_text())
        assert record["stop_iteration"] == diag["stop_iteration"] == 3
        assert record["stop_reason"] == diag["stop_reason"] == "max_iterations"
        assert diag["skills"] == record["skills"] == SKILLS[:k]
        rows = [diag[key] for key in ("alpha", "memory_losses", "grad_norms", "sleep_objective", "solver_iterations")]
        assert [len(r) for r in rows] == [3] * 5 and diag["skipped_steps"] == []
        # Eq. 1 weights: k per iteration, on the simplex; (1/2, 1/2) for two memories.
        for alpha in diag["alpha"]:
            assert len(alpha) == k and min(alpha) >= 0 and sum(alpha) == pytest.approx(1, abs=1e-9)
        for alpha, norms in zip(diag["alpha"], diag["grad_norms"], strict=True):
            if k == 2 and min(norms) > 0:
                assert alpha == pytest.approx([0.5, 0.5], abs=1e-9)
        # Sleep starts at theta_k^wake, which M_k snapshots: M_k has zero loss and gradient, so Nash masks it.
        assert diag["memory_losses"][0][-1] == diag["grad_norms"][0][-1] == diag["alpha"][0][-1] == 0.0
        assert min(diag["memory_losses"][0][:-1]) > 0 and diag["memory_losses"][-1][-1] > 0
        assert all(len(x) == k and all(v >= 0 for v in x) for x in diag["memory_losses"] + diag["grad_norms"])
        assert record["final_alpha"] == diag["alpha"][-1] and record["final_memory_losses"] == diag["memory_losses"][-1]
        # The anchor (SurgicAI setting: always on, also after the final skill) and Eq. 2's c_i for i < k only.
        assert record["anchor_lambda"] == diag["anchor_lambda"] == sleep_cfg.anchor_strength > 0
        assert len(diag["anchor_distances"]) == k - 1 and all(d > 0 for d in diag["anchor_distances"])
        # The recorded objective is alpha . L, plus the anchor term (which is >= 0).
        for alpha, losses, objective in zip(diag["alpha"], diag["memory_losses"], diag["sleep_objective"],
                                            strict=True):
            assert objective >= sum(a * x for a, x in zip(alpha, losses, strict=True)) - 1e-9
    assert results["memory_bytes_total"] == sum(results["memory_bytes"].values()) > 0
    # Videos of the first evaluation episode per skill and stage.
    assert list((out / "videos" / "skill_2_place" / "sleep").glob("approach_episode0_*.mp4"))


def test_stream_statistics_are_fixed_for_the_whole_stream(finished_run):
    out, _ = finished_run
    states = []
    for stage in sorted(out.glob("skill_*/*/pretrained_model")):
        files = list(stage.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
        assert len(files) == 1, stage
        states.append(load_file(str(files[0])))
    assert len(states) == 5
    for state in states[1:]:
        assert state.keys() == states[0].keys()
        assert all(torch.equal(state[k], states[0][k]) for k in state)


def test_union_statistics_pool_every_skill_and_first_keeps_the_first_skills(state_datasets, tmp_path):
    """--stream.stats: ``first`` = the first dataset's statistics; ``union`` = all datasets pooled (count-weighted
    mean, pooled variance), checked against the frames themselves; the std floor applies to both."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from sr_imitation.substrates.act.substrate import ACTSubstrate

    frames = {s: np.stack([np.asarray(x) for x in LeRobotDataset(f"local/sr_needle_{s}", root=state_datasets / s)
                           .hf_dataset["observation.state"]]) for s in SKILLS}
    stats = {}
    for source in ("first", "union"):
        cfg = tiny_stream_config(state_datasets, tmp_path / source, SKILLS, use_images=False)
        cfg.stream.stats = source
        substrate = ACTSubstrate(cfg)
        substrate.out.mkdir(parents=True)
        substrate.setup()
        stats[source] = substrate.stats["observation.state"]
    pooled = np.concatenate(list(frames.values()))
    np.testing.assert_allclose(stats["union"]["mean"], pooled.mean(0), atol=1e-5)
    np.testing.assert_allclose(stats["union"]["std"], pooled.std(0), rtol=1e-4)
    np.testing.assert_allclose(stats["first"]["mean"], frames[SKILLS[0]].mean(0), atol=1e-5)
    assert (stats["union"]["std"] > stats["first"]["std"]).all()  # the skills' states are offset by their index
    with pytest.raises(ValueError, match="stream.stats"):
        StreamConfig(stats="last")


def test_sleep_changes_the_policy_and_memories_stay_frozen(finished_run):
    out, _ = finished_run
    wake, sleep = _weights(out / "skill_2_place" / "wake"), _weights(out / "skill_2_place" / "sleep")
    assert any(not torch.equal(wake[k], sleep[k]) for k in wake)
    memory = load_memory(out / "memories" / "skill_1_approach.safetensors")
    assert memory.fingerprint() == load_memory(out / "memories" / "skill_1_approach.safetensors").fingerprint()


def test_resume_after_a_kill_reaches_the_same_results(finished_run, state_datasets, tmp_path, monkeypatch):
    reference_out, reference = finished_run
    out = tmp_path / "stream"
    cfg = tiny_stream_config(state_datasets, out, SKILLS, use_images=False)
    calls = {"n": 0}
    original = StreamEngine._sleep

    def killed_during_second_sleep(self, index):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("simulated kill")
        return original(self, index)

    monkeypatch.setattr(StreamEngine, "_sleep", killed_during_second_sleep)
    with pytest.raises(KeyboardInterrupt):
        train_stream(cfg, fake_env_factory)
    monkeypatch.setattr(StreamEngine, "_sleep", original)
    progress = json.loads((out / "progress.json").read_text())["completed"]
    assert "3.wake.eval" in progress and "3.sleep" not in progress
    assert not (out / "results.json").exists()
    # Without --resume nothing is overwritten.
    with pytest.raises(FileExistsError, match="--resume=true"):
        train_stream(cfg, fake_env_factory)
    cfg.resume = True
    resumed = train_stream(cfg, fake_env_factory)
    assert resumed["success_matrix_per_unit"] == reference["success_matrix_per_unit"]
    assert resumed["metrics"] == reference["metrics"]
    final, ref = _weights(out / "skill_3_insert" / "sleep"), _weights(reference_out / "skill_3_insert" / "sleep")
    assert all(torch.equal(final[k], ref[k]) for k in ref)


def test_resume_refuses_changed_settings_and_missing_files(finished_run, tmp_path):
    reference_out, _ = finished_run
    out = tmp_path / "copy"
    shutil.copytree(reference_out, out)
    cfg = tiny_stream_config(Path(json.loads((out / "train_config.json").read_text())["stream"]["dataset_root"]),
                             out, SKILLS, use_images=False)
    cfg.resume = True
    cfg.seed = 8
    with pytest.raises(SettingsMismatchError, match=r"settings_fingerprint.json: cannot resume with different "
                                                    r"settings \(stored -> requested\): seed: 7 -> 8 \("):
        train_stream(cfg, fake_env_factory)
    cfg.seed = 7
    progress = json.loads((out / "progress.json").read_text())
    del progress["completed"]["3.sleep.eval"]
    del progress["sha256"]
    write_checked_json(out / "progress.json", progress)
    (out / "memories" / "skill_2_place.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="skill_2_place.safetensors"):
        train_stream(cfg, fake_env_factory)
    (out / "memories" / "skill_2_place.safetensors").write_bytes(b"garbage")
    with pytest.raises(CorruptFileError, match="skill_2_place.safetensors"):
        train_stream(cfg, fake_env_factory)


def test_dataset_problems_are_named(image_datasets, state_datasets, tmp_path):
    # The policy expects a camera (first skill has one); the second skill's dataset has none.
    mixed = tmp_path / "mixed"
    shutil.copytree(image_datasets / "approach", mixed / "approach")
    shutil.copytree(state_datasets / "place", mixed / "place")
    with pytest.raises(DatasetMismatchError, match=r"place/meta/info.json: missing feature 'observation.images.wrist'"):
        train_stream(tiny_stream_config(mixed, tmp_path / "o1", ["approach", "place"]), fake_env_factory)
    # Another action size.
    other = tmp_path / "other"
    shutil.copytree(state_datasets / "approach", other / "approach")
    make_skill_dataset(other, "place", 1, image=False, action_dim=5)
    with pytest.raises(DatasetMismatchError, match=r"feature 'action' has shape \(5,\), the policy expects \(7,\)"):
        train_stream(tiny_stream_config(other, tmp_path / "o2", ["approach", "place"], use_images=False),
                     fake_env_factory)
    # Missing dataset.
    with pytest.raises(DatasetMismatchError, match="not a LeRobot dataset"):
        train_stream(tiny_stream_config(tmp_path / "nowhere", tmp_path / "o3", ["approach"]), fake_env_factory)
    # State-only training on a dataset without cameras asks for images: clear hint.
    with pytest.raises(DatasetMismatchError, match="use_images=false"):
        train_stream(tiny_stream_config(state_datasets, tmp_path / "o4", ["approach"]), fake_env_factory)


def test_non_finite_loss_stops_wake_with_the_dataset_named(state_datasets, tmp_path):
    root = tmp_path / "nan"
    make_skill_dataset(root, "approach", 0, image=False)
    cfg = tiny_stream_config(root, tmp_path / "o", ["approach"], use_images=False)
    cfg.policy.optimizer_lr = float("inf")
    with pytest.raises(NonFiniteLossError, match=r"skill 'approach' \(.*nan/approach\)"):
        train_stream(cfg, fake_env_factory)


def test_image_stream_runs_end_to_end(image_datasets, tmp_path):
    cfg = tiny_stream_config(image_datasets, tmp_path / "img", SKILLS[:2])
    results = train_stream(cfg, fake_env_factory)
    memory = load_memory(tmp_path / "img" / "memories" / "skill_1_approach.safetensors")
    assert memory.tensors["input.observation.images.wrist"].dtype == torch.uint8
    assert results["skills"] == SKILLS[:2] and "sleep" in results["stages"][1]


def test_in_memory_dataset_serves_the_same_items_as_lerobot(image_datasets):
    from sr_imitation.substrates.act.data import load_skill_data
    from tests.substrates.act.helpers import tiny_policy

    cfg = tiny_policy()
    from tests.substrates.act.test_policy import _features

    _features(cfg)
    fast = load_skill_data("place", image_datasets / "place", "local/sr_needle_place", cfg, 0.3, 0)
    slow = load_skill_data("place", image_datasets / "place", "local/sr_needle_place", cfg, 0.3, 0,
                           materialize=False)
    assert fast.train_indices == slow.train_indices and len(fast.dataset) == len(slow.dataset) == 30
    for i in (0, 5, 8, 9, 10, 29):  # includes the padded chunks at the ends of episodes
        a, b = fast.dataset[i], slow.dataset[i]
        for key in ("observation.state", "observation.images.wrist", "action", "action_is_pad"):
            assert torch.allclose(a[key].float(), b[key].float(), atol=1e-6), (i, key)
    assert bool(fast.dataset[9]["action_is_pad"][1]) and not bool(fast.dataset[0]["action_is_pad"].any())


def test_the_run_log_has_wake_epochs_sleep_iterations_and_phases(finished_run):
    from sr_imitation.infra.runlog import read_log

    out, results = finished_run
    records = read_log(out / "log.jsonl")
    wake = [r for r in records if r["kind"] == "wake"]
    assert {r["stage"] for r in wake} == {1, 2, 3} and all("val_l1" in r and "l1_loss" in r for r in wake)
    sleep = [r for r in records if r["kind"] == "sleep"]
    assert {r["stage"] for r in sleep} == {2, 3}
    stops = {st["stage"] + 1: st["sleep"]["stop_iteration"] for st in results["stages"] if "sleep" in st}
    assert stops == {s: sum(r["stage"] == s for r in sleep) for s in (2, 3)}
    phases = [(r["stage"], r["phase"]) for r in records if r["kind"] == "phase"]
    recorded = [(st["stage"] + 1, p) for st in results["stages"] for p in ("wake", "memory", "wake.eval", "sleep",
                                                                           "sleep.eval") if p in st]
    assert sorted(phases) == sorted(recorded) and (3, "sleep.eval") in phases
