"""A SAC wake killed between episodes resumes from its snapshot bit for bit (sr_imitation.substrates.sac.wake_snapshot):
the wake alone, the oracle's one training phase, and a stream run through ``--resume``."""

from __future__ import annotations

import dataclasses
import itertools
import json
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from sr_imitation.core.excitability import ExcitabilityConfig
from sr_imitation.envs.metaworld import tasks
from sr_imitation.envs.metaworld.tasks import SkillEnv
from sr_imitation.io import CorruptFileError, load_checked_safetensors
from sr_imitation.reporting.summary import phase_seconds
from sr_imitation.substrates.sac import wake as rl_wake
from sr_imitation.substrates.sac.config import CriticMemoryConfig, EvalConfig, SACConfig, SkillBudget, WakeConfig
from sr_imitation.substrates.sac.mt_joint import run_mt_joint
from sr_imitation.substrates.sac.sac import SACAgent
from sr_imitation.substrates.sac.trainer import SACTrainer
from sr_imitation.substrates.sac.wake import train_skill
from tests.substrates.sac.test_trainer import SimulatedKillError as Killed  # stands for kill -9
from tests.substrates.sac.test_trainer import tiny_config

SAC = SACConfig(hidden_dim=32, batch_size=16, utd_ratio=0.5, warmup_steps=40, buffer_size=5000)
WAKE = WakeConfig(budgets={"reach": SkillBudget(7, 4, 2)}, rolling_window=3, early_stopping=False,
                  snapshot_every_s=0.0)  # a snapshot after every episode
MEMORY = CriticMemoryConfig(buffer_size=32, validation_chunk=5, validation_max_rounds=1)


def _kill_at_reset(monkeypatch, n: int) -> None:
    """Every SkillEnv raises :class:`Killed` at its process's n-th episode start."""
    calls = {"n": 0}
    reset = SkillEnv.reset

    def counting(self, configuration=None):
        calls["n"] += 1
        if calls["n"] == n:
            raise Killed
        return reset(self, configuration)

    monkeypatch.setattr(tasks.SkillEnv, "reset", counting)


def _wake(snapshot: Path | None, every_s: float = 0.0):
    """One wake on reach as a fresh process would run it (seeds first), with a snapshot every ``every_s``."""
    torch.manual_seed(11)
    np.random.seed(12)
    agent = SACAgent(SAC, ExcitabilityConfig())
    with SkillEnv("reach-v3", seed=5, max_episode_steps=25) as env:
        result, memory = train_skill(agent, env, 0, SAC, dataclasses.replace(WAKE, snapshot_every_s=every_s),
                                     ExcitabilityConfig(), MEMORY, seed=5, progress=False, snapshot=snapshot)
    return result, memory, agent


def _same_wake(a, b) -> None:
    (ra, ma, agent_a), (rb, mb, agent_b) = a, b
    assert ra.episode_rewards == rb.episode_rewards and ra.episode_successes == rb.episode_successes
    assert (ra.episodes, ra.env_steps, ra.updates, ra.stop_reason) == (rb.episodes, rb.env_steps, rb.updates,
                                                                       rb.stop_reason)
    assert ra.last_update == rb.last_update and ra.critic_validation == rb.critic_validation
    for (name, x), (_, y) in zip(agent_a.state_dict().items(), agent_b.state_dict().items(), strict=True):
        assert torch.equal(x, y), name
    for name in ("actor_optimizer", "critic_optimizer", "alpha_optimizer"):
        sa, sb = getattr(agent_a, name).state_dict()["state"], getattr(agent_b, name).state_dict()["state"]
        assert all(torch.equal(sa[i][k], sb[i][k]) for i in sa for k in sa[i]), name
    assert ma.tensors.keys() == mb.tensors.keys()
    assert all(torch.equal(ma.tensors[n], mb.tensors[n]) for n in ma.tensors)  # the frozen critic memory


@pytest.mark.parametrize("kill_at", [2, 4, 7])  # during the warm-up, after it, before the last episode
def test_a_wake_killed_between_episodes_resumes_bit_for_bit(tmp_path, monkeypatch, kill_at):
    whole = _wake(None)
    assert whole[0].episodes == 7 and whole[0].updates > 0  # the budget, with updates after the warm-up
    snapshot = tmp_path / "wake_snapshot.safetensors"
    with monkeypatch.context() as m:
        _kill_at_reset(m, kill_at)
        with pytest.raises(Killed):
            _wake(snapshot)
    _, header = load_checked_safetensors(snapshot)
    assert header["env_steps"] == 25 * (kill_at - 1)  # every finished episode is in it
    resumed = _wake(snapshot)
    _same_wake(whole, resumed)
    assert not snapshot.exists()  # removed when the wake ended


def test_no_snapshot_is_written_before_its_time_and_a_foreign_one_is_refused(tmp_path, monkeypatch):
    snapshot = tmp_path / "wake_snapshot.safetensors"
    with monkeypatch.context() as m:
        _kill_at_reset(m, 5)
        with pytest.raises(Killed):
            _wake(snapshot, every_s=3600.0)
    assert not snapshot.exists()  # an hour had not passed: a killed wake starts again, same numbers
    with monkeypatch.context() as m:
        _kill_at_reset(m, 3)
        with pytest.raises(Killed):
            _wake(snapshot)
    torch.manual_seed(11)
    agent = SACAgent(SAC, ExcitabilityConfig())
    with SkillEnv("reach-v3", seed=6, max_episode_steps=25) as env, pytest.raises(CorruptFileError,
                                                                                  match="wake_snapshot.safetensors"):
        train_skill(agent, env, 0, SAC, WAKE, ExcitabilityConfig(), MEMORY, seed=6, progress=False,
                    snapshot=snapshot)  # another seed's wake


def test_the_oracle_s_training_killed_inside_resumes_to_the_same_results(tmp_path, monkeypatch):
    config = {"eval": EvalConfig(episodes=2, videos_per_skill=0),
              "wake": WakeConfig(budget_scale=0.002, snapshot_every_s=0.0)}
    whole = run_mt_joint(tiny_config(tmp_path / "whole", **config), episodes=2000)  # 4 episodes
    with monkeypatch.context() as m:
        _kill_at_reset(m, 4)
        with pytest.raises(Killed):
            run_mt_joint(tiny_config(tmp_path / "killed", **config), episodes=2000)
    assert (tmp_path / "killed" / "train_snapshot.safetensors").is_file()
    resumed = run_mt_joint(tiny_config(tmp_path / "killed", resume=True, **config), episodes=2000)
    assert resumed["success_matrix"] == whole["success_matrix"]
    weights = [load_checked_safetensors(tmp_path / run / "agent.safetensors")[0] for run in ("whole", "killed")]
    assert all(torch.equal(weights[0][n], weights[1][n]) for n in weights[0])
    assert not (tmp_path / "killed" / "train_snapshot.safetensors").exists()


# SR; CLEAR, whose wake hooks mix replayed transitions into every update (drawn from the hooks' generator, which
# travels with the snapshot); A-GEM, whose reference gradient travels with it too (its wake state as a tensor).
# PCGrad's and Nash-MTL's state (a JSON record through the same snapshot frame) is checked where it matters, with three
# gradients: tests/stream/test_wake_hooks_resume.py and tests/core/test_aggregators.py.
@pytest.mark.parametrize(("method", "snapshots"), [("sr", True), ("clear", True), ("agem", True)])
def test_a_stream_killed_inside_a_wake_resumes_to_the_same_results(tmp_path, monkeypatch, method, snapshots):
    config = {"eval": EvalConfig(episodes=2, videos_per_skill=0),
              "wake": WakeConfig(budget_scale=0.004, snapshot_every_s=0.0),
              "method": method}
    SACTrainer(tiny_config(tmp_path / "whole", **config)).run()
    with monkeypatch.context() as m:
        _kill_at_reset(m, 10)  # stage 2's wake (reach: 6 episodes, its evaluation: 2)
        with pytest.raises(Killed):
            SACTrainer(tiny_config(tmp_path / "killed", **config)).run()
    stage = tmp_path / "killed" / "stages" / "02_door-open"
    assert (stage / "wake_snapshot.safetensors").is_file() == snapshots
    if method != "sr":  # the hooks had drawn and counted before the kill: their state is in the snapshot
        tensors, header = load_checked_safetensors(stage / "wake_snapshot.safetensors")
        assert header["method_hooks"] == method and header["hooks"]["updates"] > 0 and "hooks.generator" in tensors
        if method == "agem":
            assert tensors["hooks.method.reference"].ndim == 1
    # the interval may change on resume (allow-listed: it never changes results); the snapshot found is still used
    resumed = config | {"wake": WakeConfig(budget_scale=0.004, snapshot_every_s=-1.0)}
    SACTrainer(tiny_config(tmp_path / "killed", resume=True, **resumed)).run()
    runs = [json.loads((tmp_path / run / "results.json").read_text()) for run in ("whole", "killed")]
    assert runs[0]["success_matrix"] == runs[1]["success_matrix"] and runs[0]["metrics"] == runs[1]["metrics"]
    for name in ("wake", "sleep") if method == "sr" else ("wake",):  # the baselines do not sleep
        a, b = (load_checked_safetensors(tmp_path / run / "stages" / "02_door-open" / name / "agent.safetensors")[0]
                for run in ("whole", "killed"))
        assert all(torch.equal(a[n], b[n]) for n in a), name
    assert not (stage / "wake_snapshot.safetensors").exists()


@pytest.mark.parametrize("oracle", [False, True])
def test_a_resumed_sac_wake_writes_its_whole_time_as_its_phase_s_time(tmp_path, monkeypatch, oracle):
    """The phase's ``seconds`` in progress.json (and a stage's in results.json) count the time the killed process
    spent in the wake, carried by the snapshot, not only the resumed process's: the wake loop's clock runs 1000 s a
    reading, so the snapshot carries >= 1000 s while the resumed process's own clock runs at its normal pace."""
    config = {"eval": EvalConfig(episodes=2, videos_per_skill=0),
              "wake": WakeConfig(budget_scale=0.002 if oracle else 0.004, snapshot_every_s=0.0)}
    out = tmp_path / "killed"

    def run(**resume):
        cfg = tiny_config(out, **resume, **config)
        return run_mt_joint(cfg, episodes=2000) if oracle else SACTrainer(cfg).run()

    with monkeypatch.context() as m:
        _kill_at_reset(m, 4 if oracle else 10)  # inside the oracle's training / stage 2's wake
        ticks = itertools.count()
        m.setattr(rl_wake, "time", types.SimpleNamespace(perf_counter=lambda: 1000.0 * next(ticks)))
        with pytest.raises(Killed):
            run()
    snapshot = out / ("train_snapshot.safetensors" if oracle else "stages/02_door-open/wake_snapshot.safetensors")
    carried = load_checked_safetensors(snapshot)[1]["seconds"]
    assert carried >= 1000.0
    run(resume=True)
    completed = json.loads((out / "progress.json").read_text())["completed"]
    record = completed["1.train"] if oracle else completed["2.wake"]
    assert record["wake"]["seconds"] >= carried  # the wake's own record always counted it
    assert carried <= record["seconds"] < carried + 600.0  # the phase's time now does too
    assert phase_seconds(out) >= carried
    if not oracle:
        stage = json.loads((out / "results.json").read_text())["stages"][1]
        assert stage["seconds"] >= carried
