"""``sr-sac-sleep``: a finished SAC run's last sleep redone from its weight store with other sleep settings
(issue 59): the repeat of the source's own sleep is bit-identical, a changed setting changes only the sleep, and
what a re-sleep may not change, or a damaged store, is refused before anything is written."""

from __future__ import annotations

import pytest
import torch

from sr_imitation.experiments.archive import archive_run, weight_store
from sr_imitation.io import CorruptFileError, load_checked_safetensors, read_checked_json
from sr_imitation.substrates.sac.config import EvalConfig
from sr_imitation.substrates.sac.resleep import RESLEEP_FILE, ResleepConfig, main, resleep
from sr_imitation.substrates.sac.trainer import SACTrainer
from tests.substrates.sac.test_trainer import tiny_config

SLEEP = ("stages", "02_door-open", "sleep", "agent.safetensors")


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A finished two-skill SR run, archived with its weights: (archived run, its store, its results)."""
    root = tmp_path_factory.mktemp("resleep")
    results = SACTrainer(tiny_config(root / "runs" / "sr_seed3", eval=EvalConfig(episodes=2, videos_per_skill=0))).run()
    archived = archive_run(root / "runs" / "sr_seed3", root / "archive", "sr_seed3", keep_weights=True)
    return archived, weight_store(root / "archive") / "sr_seed3", results


def _weights(path):
    return load_checked_safetensors(path.joinpath(*SLEEP))[0]


def test_a_repeat_of_the_sleep_from_the_store_is_bit_identical(tmp_path, stored):
    archived, store, source = stored
    out = tmp_path / "repeat"
    results = resleep(ResleepConfig(source=store, archived=archived, output_dir=out))
    assert results["success_matrix"] == source["success_matrix"] and results["metrics"] == source["metrics"]
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}  # noqa: E731
    assert strip(results["stages"][1]["sleep"]) == strip(source["stages"][1]["sleep"])
    a, b = _weights(store), _weights(out)
    assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)
    record = read_checked_json(out / RESLEEP_FILE)
    assert record["stage"] == 2 and record["changed"] == [] and record["source"] == str(store)


def test_a_changed_sleep_setting_changes_the_sleep_only(tmp_path, stored):
    archived, store, source = stored
    out = tmp_path / "lr"
    main([f"--source={store}", f"--output_dir={out}", "--changes=[--sleep.lr=0.05,--sleep.early_stop_tol=0]"])
    results = read_checked_json(out / "results.json")
    timeless = lambda stage: {k: v for k, v in stage.items() if k != "seconds"}  # noqa: E731 (memory phases redone)
    assert timeless(results["stages"][0]) == timeless(source["stages"][0])  # stage 1 is the source's, as recorded
    assert results["stages"][1]["eval_after_wake"] == source["stages"][1]["eval_after_wake"]
    assert results["stages"][1]["sleep"]["stop_iteration"] == 12  # the whole budget: no plateau stop
    a, b = _weights(store), _weights(out)
    assert any(not torch.equal(a[n], b[n]) for n in a)
    wake = ("stages", "02_door-open", "wake", "agent.safetensors")
    a, b = (load_checked_safetensors(run.joinpath(*wake))[0] for run in (store, out))
    assert all(torch.equal(a[n], b[n]) for n in a)  # the wake is the source's
    assert read_checked_json(out / RESLEEP_FILE)["changed"] == ["sleep.early_stop_tol", "sleep.lr"]
    assert set(results) == set(source)  # the same results schema


def test_what_a_resleep_may_not_change_is_refused_before_anything_is_written(tmp_path, stored):
    archived, store, _ = stored
    out = tmp_path / "bad"
    with pytest.raises(ValueError, match=r"changes: a re-sleep may change the sleep's settings only; sac.hidden_dim"):
        resleep(ResleepConfig(source=store, output_dir=out, changes=["--sac.hidden_dim=16"]))
    with pytest.raises(ValueError, match=r"stage: only the source's last stage \(2\)"):
        resleep(ResleepConfig(source=store, output_dir=out, stage=1))
    assert not out.exists()
    damaged = store / "stages" / "01_reach" / "memory.safetensors"
    data = damaged.read_bytes()
    damaged.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    try:
        with pytest.raises(CorruptFileError, match=r"01_reach/memory.safetensors.*differs from its checksum"):
            resleep(ResleepConfig(source=store, archived=archived, output_dir=out))
    finally:
        damaged.write_bytes(data)
    assert not out.exists()


def test_a_killed_resleep_continues_with_the_same_command_and_another_is_refused(tmp_path, stored):
    archived, store, source = stored
    out = tmp_path / "killed"
    cfg = ResleepConfig(source=store, output_dir=out, changes=["--sleep.lr=0.05"])
    full = resleep(ResleepConfig(source=store, output_dir=tmp_path / "full", changes=["--sleep.lr=0.05"]))

    class KillError(RuntimeError):
        pass

    def kill(k, phase):
        if phase == "sleep":
            raise KillError

    import sr_imitation.substrates.sac.trainer as trainer

    original = trainer.SACTrainer.__init__

    def killing(self, run_cfg, after_stage=None, after_phase=None):
        original(self, run_cfg, after_stage, kill if run_cfg.resume else None)

    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(trainer.SACTrainer, "__init__", killing)
    with pytest.raises(KillError):
        resleep(cfg)
    monkeypatch.undo()
    assert (out / RESLEEP_FILE).is_file() and not (out / "results.json").exists()
    assert resleep(cfg)["metrics"] == full["metrics"]
    with pytest.raises(ValueError, match=r"resleep.json: a re-sleep of another source or with other changes \(changes"):
        resleep(ResleepConfig(source=store, output_dir=out, changes=["--sleep.lr=0.01"]))
