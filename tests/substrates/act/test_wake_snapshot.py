"""An ACT wake killed inside an epoch resumes from its last snapshot bit for bit
(sr_imitation.substrates.act.wake_snapshot): a stream's wake with memories attached (the distillation's sampler), ACT's
VAE and dropout (the global generator) and the best epoch's weights kept, and the MT-Joint oracle's one training phase.
The references never write a snapshot, so the checks also show that writing one draws nothing."""

from __future__ import annotations

import itertools
import json
import types
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.io import CorruptFileError, load_checked_safetensors
from sr_imitation.reporting.summary import phase_seconds
from sr_imitation.substrates.act import wake, wake_snapshot
from sr_imitation.substrates.act.mt_joint import run_mt_joint
from sr_imitation.substrates.act.substrate import WAKE_SNAPSHOT
from sr_imitation.substrates.act.trainer import train_stream
from sr_imitation.substrates.act.wake import WakeConfig
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config

EPOCHS, STEPS = 4, 2  # per wake: 4 epochs of 2 updates


class Killed(BaseException):
    """Stands for kill -9 (not an Exception: nothing may catch it)."""


def _config(datasets: Path, out: Path, skills: list[str], method: str = "sr", every_s: float = 0.0):
    """Snapshots at every epoch's end (``every_s`` 0) or never (negative)."""
    cfg = tiny_stream_config(datasets, out, skills, use_images=False, dropout=0.1, use_vae=True)
    cfg.wake.max_epochs = cfg.wake.min_epochs = EPOCHS
    cfg.wake.snapshot_every_s = every_s
    cfg.wake.restore = "best"
    cfg.method = method
    return cfg


def _kill_at_update(monkeypatch, n: int) -> None:
    """The n-th optimizer update of the process (1-based) raises :class:`Killed` before it changes anything (LeRobot's
    ``update_policy`` or, with a method's hooks, ``hooked_update``)."""
    calls = {"n": 0}

    def counting(update):
        def wrapped(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] == n:
                raise Killed
            return update(*args, **kwargs)
        return wrapped

    for name in ("update_policy", "hooked_update"):
        monkeypatch.setattr(wake, name, counting(getattr(wake, name)))


def _weights(folder: Path) -> dict[str, torch.Tensor]:
    return load_file(folder / "pretrained_model" / "model.safetensors")


def _same_weights(a: Path, b: Path) -> None:
    wa, wb = _weights(a), _weights(b)
    assert wa.keys() == wb.keys()
    assert all(torch.equal(wa[k], wb[k]) for k in wa), a


@pytest.fixture(scope="module")
def never_stopped(state_datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("never_stopped") / "stream"
    results = train_stream(_config(state_datasets, out, SKILLS[:2], every_s=-1.0), fake_env_factory)  # none at all
    return out, results


# Updates 1-8 are the first skill's wake, 9-16 the second's (with the first skill's memory attached).
@pytest.mark.parametrize(("kill_at", "epochs_in_snapshot"), [
    (10, None),  # inside the second wake's first epoch: no snapshot yet, the wake starts again
    (13, 2),  # at the start of its third epoch
    (16, 3),  # at its very last update
    (4, 1),  # inside the first wake (no memories)
])
def test_a_stream_wake_killed_inside_an_epoch_resumes_bit_for_bit(never_stopped, state_datasets, tmp_path,
                                                                  monkeypatch, kill_at, epochs_in_snapshot):
    reference, expected = never_stopped
    out = tmp_path / "stream"
    stage = "skill_2_place" if kill_at > EPOCHS * STEPS else "skill_1_approach"
    with monkeypatch.context() as m:
        _kill_at_update(m, kill_at)
        with pytest.raises(Killed):
            train_stream(_config(state_datasets, out, SKILLS[:2]), fake_env_factory)
    snapshot = out / stage / WAKE_SNAPSHOT
    if epochs_in_snapshot is None:
        assert not snapshot.exists()
    else:
        _, header = load_checked_safetensors(snapshot)
        assert header["epochs"] == epochs_in_snapshot and header["steps"] == epochs_in_snapshot * STEPS
        assert header["best_state"] is True  # --wake.restore=best: the best epoch's weights travel with it
    cfg = _config(state_datasets, out, SKILLS[:2], every_s=-1.0)  # may change on resume: a found one is still used
    cfg.resume = True
    results = train_stream(cfg, fake_env_factory)
    assert not snapshot.exists()  # removed when the wake ends
    assert results["success_matrix_per_unit"] == expected["success_matrix_per_unit"]
    assert results["metrics"] == expected["metrics"]
    for name in ("skill_1_approach", "skill_2_place"):
        _same_weights(out / name / "wake", reference / name / "wake")
        history = json.loads((out / name / "wake" / "wake_history.json").read_text())
        assert history == json.loads((reference / name / "wake" / "wake_history.json").read_text())
    _same_weights(out / "skill_2_place" / "sleep", reference / "skill_2_place" / "sleep")


def test_a_replay_wake_killed_inside_resumes_bit_for_bit_with_its_hooks(state_datasets, tmp_path, monkeypatch):
    """Experience replay's wake hooks draw the replayed frames from their own generator at every update: it travels
    with the snapshot (``resumable_wake_hooks``), so the resumed wake replays the same frames."""
    expected = train_stream(_config(state_datasets, tmp_path / "whole", SKILLS[:2], "replay", every_s=-1.0),
                            fake_env_factory)
    out = tmp_path / "killed"
    with monkeypatch.context() as m:
        _kill_at_update(m, EPOCHS * STEPS + 2 * STEPS + 1)  # the second wake's third epoch
        with pytest.raises(Killed):
            train_stream(_config(state_datasets, out, SKILLS[:2], "replay"), fake_env_factory)
    tensors, header = load_checked_safetensors(out / "skill_2_place" / WAKE_SNAPSHOT)
    assert header["method_hooks"] == "replay" and header["hooks"]["updates"] == 2 * STEPS
    assert "hooks.generator" in tensors
    cfg = _config(state_datasets, out, SKILLS[:2], "replay")
    cfg.resume = True
    results = train_stream(cfg, fake_env_factory)
    assert results["success_matrix_per_unit"] == expected["success_matrix_per_unit"]
    _same_weights(out / "skill_2_place" / "wake", tmp_path / "whole" / "skill_2_place" / "wake")


def test_the_oracles_training_killed_inside_resumes_bit_for_bit(state_datasets, tmp_path, monkeypatch):
    expected = run_mt_joint(_config(state_datasets, tmp_path / "whole", SKILLS[:2], every_s=-1.0), fake_env_factory)
    out = tmp_path / "killed"
    with monkeypatch.context() as m:
        _kill_at_update(m, 2 * STEPS * 2 + 1)  # the union's epochs are 2 x 2 updates: inside the third epoch
        with pytest.raises(Killed):
            run_mt_joint(_config(state_datasets, out, SKILLS[:2]), fake_env_factory)
    assert load_checked_safetensors(out / WAKE_SNAPSHOT)[1]["epochs"] == 2
    cfg = _config(state_datasets, out, SKILLS[:2])
    cfg.resume = True
    results = run_mt_joint(cfg, fake_env_factory)
    assert not (out / WAKE_SNAPSHOT).exists()
    assert results["success_matrix_per_unit"] == expected["success_matrix_per_unit"]
    _same_weights(out / "mt_joint" / "wake", tmp_path / "whole" / "mt_joint" / "wake")


def _slow_clock(monkeypatch) -> None:
    """The wake loop's clock runs 1000 s per reading: a killed wake's snapshot then carries >= 1000 s of wall time."""
    ticks = itertools.count()
    monkeypatch.setattr(wake, "time", types.SimpleNamespace(perf_counter=lambda: 1000.0 * next(ticks)))


@pytest.mark.parametrize("oracle", [False, True])
def test_a_resumed_wake_reports_the_time_before_its_snapshot_too(state_datasets, tmp_path, monkeypatch, oracle):
    """A phase's time is measured by the process that finishes it; a wake resumed from its snapshot adds the time
    the snapshot carries, so a run's compute time (reporting.summary.phase_seconds) counts the killed part."""
    run = run_mt_joint if oracle else train_stream
    out = tmp_path / "run"
    with monkeypatch.context() as m:
        _kill_at_update(m, 2 * STEPS * 2 + 1 if oracle else EPOCHS * STEPS + 2 * STEPS + 1)  # the 3rd epoch of a wake
        _slow_clock(m)
        with pytest.raises(Killed):
            run(_config(state_datasets, out, SKILLS[:2]), fake_env_factory)
    snapshot = out / WAKE_SNAPSHOT if oracle else out / "skill_2_place" / WAKE_SNAPSHOT
    carried = load_checked_safetensors(snapshot)[1]["seconds"]
    assert carried >= 1000.0
    cfg = _config(state_datasets, out, SKILLS[:2])
    cfg.resume = True
    run(cfg, fake_env_factory)
    progress = json.loads((out / "progress.json").read_text())["completed"]
    wake_seconds = progress["1.wake"]["seconds"] if oracle else progress["2.wake"]["seconds"]
    assert carried <= wake_seconds < carried + 600.0
    assert phase_seconds(out) >= carried


def test_a_snapshot_of_another_wake_or_a_damaged_one_is_refused_naming_the_file(state_datasets, tmp_path,
                                                                                 monkeypatch):
    out = tmp_path / "stream"
    with monkeypatch.context() as m:
        _kill_at_update(m, 5)
        with pytest.raises(Killed):
            train_stream(_config(state_datasets, out, SKILLS[:2]), fake_env_factory)
    snapshot = out / "skill_1_approach" / WAKE_SNAPSHOT
    _, header = load_checked_safetensors(snapshot)
    identity = {k: header[k] for k in ("skill", "seed", "train_frames", "steps_per_epoch", "max_epochs",
                                       "method_hooks")}
    cfg = _config(state_datasets, out, SKILLS[:2])
    generators = wake_snapshot.WakeGenerators(torch.Generator(), torch.Generator(), None)
    policy = torch.nn.Linear(2, 2)
    with pytest.raises(CorruptFileError, match=r"wake_snapshot.safetensors: wake snapshot of .*'seed': 8"):
        wake_snapshot.load(snapshot, identity | {"seed": 8}, policy, torch.optim.AdamW(policy.parameters()),
                           generators)
    with pytest.raises(CorruptFileError, match="wake_snapshot.safetensors: the snapshot's policy does not fit"):
        wake_snapshot.load(snapshot, identity, policy, torch.optim.AdamW(policy.parameters()), generators)
    data = bytearray(snapshot.read_bytes())
    data[-3] ^= 0xFF
    snapshot.write_bytes(bytes(data))
    cfg.resume = True
    with pytest.raises(CorruptFileError, match="wake_snapshot.safetensors"):
        train_stream(cfg, fake_env_factory)


def test_no_snapshot_is_written_with_a_negative_interval(state_datasets, tmp_path, monkeypatch):
    out = tmp_path / "stream"
    with monkeypatch.context() as m:
        _kill_at_update(m, 7)  # after three epochs of the first wake
        with pytest.raises(Killed):
            train_stream(_config(state_datasets, out, SKILLS[:2], every_s=-1.0), fake_env_factory)
    assert (out / "settings_fingerprint.json").is_file() and not list(out.rglob(WAKE_SNAPSHOT))  # it had started
    with pytest.raises(ValueError, match="wake.snapshot_every_s must be a number"):
        WakeConfig(snapshot_every_s=float("nan"))
