"""Stream trainer: end-to-end on a tiny 2-skill stream, resume after a kill, output-dir safety, CLI configs,
paired evaluation (the same configurations for a skill at every stage and right after its wake)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import draccus
import pytest
import torch

from sr_imitation.envs.metaworld.tasks import SkillEnv
from sr_imitation.infra.fingerprint import SettingsMismatchError
from sr_imitation.io import CorruptFileError, load_checked_safetensors
from sr_imitation.reporting.results import RESULTS_VERSION
from sr_imitation.reporting.summary import group_runs, render_markdown, summarize
from sr_imitation.stream.config import StreamSleepConfig
from sr_imitation.substrates.sac.config import (
    CriticMemoryConfig,
    EvalConfig,
    RLTrainConfig,
    SACConfig,
    StreamConfig,
    WakeConfig,
)
from sr_imitation.substrates.sac.sac import SACAgent
from sr_imitation.substrates.sac.trainer import SACTrainer

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def tiny_config(out: Path, skills: list[str] | None = None, extend_from: Path | None = None,
                **overrides) -> RLTrainConfig:
    stream = StreamConfig(skills=skills or ["reach-v3", "door-open-v3"], extend_from=extend_from)
    base = {
        "output_dir": out, "seed": 3, "stream": stream, "max_episode_steps": 30,
        "sac": SACConfig(hidden_dim=32, batch_size=16, utd_ratio=0.5, warmup_steps=40, buffer_size=5000),
        "wake": WakeConfig(budget_scale=0.002),
        "sleep": StreamSleepConfig.mt5(max_iterations=12, early_stop_window=5, fw_iterations=5, batch_size=16),
        "memory": CriticMemoryConfig(buffer_size=32, validation_chunk=5, validation_max_rounds=1),
        "eval": EvalConfig(episodes=2, video_height=64, video_width=64), "progress": False, "plots": False,
    }
    base.update(overrides)
    return RLTrainConfig(**base)


def stop_after(out: Path, point: tuple[int, str], **cfg) -> None:
    """A run of ``tiny_config(out, **cfg)`` killed right after phase ``point`` (stage index, phase) completed."""

    def kill(k, phase):
        if (k, phase) == point:
            raise SimulatedKillError

    with pytest.raises(SimulatedKillError):
        SACTrainer(tiny_config(out, **cfg), after_phase=kill).run()


class SimulatedKillError(RuntimeError):
    pass


def test_stream_end_to_end_and_resume_after_kill(tmp_path):
    full = SACTrainer(tiny_config(tmp_path / "full", plots=True)).run()
    assert full["skills"] == ["reach", "door-open"]
    assert len(full["success_matrix"]) == 2 and full["success_matrix"][0][1] is None
    assert set(full["metrics"]) == {"afsr", "prs", "bwt", "bwt_wake", "spi"}
    assert full["substrate"] == "sac" and full["label"] == "sr" and full["eval_units"] == 1
    assert "sleep" in full["stages"][1] and "sleep" not in full["stages"][0]
    # After-wake evaluation (on by default): stage 1 has no sleep and reuses its stage evaluation; stage 2 is
    # evaluated before its sleep on the same configurations as its stage evaluation.
    wake_rows = [stage["eval_after_wake"] for stage in full["stages"]]
    assert [row["reused_stage_evaluation"] for row in wake_rows] == [True, False]
    assert wake_rows[0]["success_rate"] == full["success_matrix"][0][0]
    assert wake_rows[1]["configurations"] == full["stages"][1]["eval"][1]["configurations"]
    assert full["success_after_own_wake"] == [row["success_rate"] for row in wake_rows]
    s_final, w = full["success_matrix"], full["success_after_own_wake"]
    assert full["metrics"]["bwt_wake"]["final"] == pytest.approx(s_final[1][0] - w[0])
    assert full["metrics"]["bwt"]["final"] == pytest.approx(s_final[1][0] - s_final[0][0])
    assert full["spi_features"] == [0, 1, 2, 3] and full["results_version"] == RESULTS_VERSION == 5
    assert len(full["stages"][1]["sleep"]["frozen_critic_value_change"]) == 2
    assert (tmp_path / "full" / "success_matrix.png").is_file() and (tmp_path / "full" / "metrics.png").is_file()
    assert "BWT_wake" in (tmp_path / "full" / "results.md").read_text()
    assert f"| sr | 3 | {tmp_path / 'full'} |" in render_markdown(summarize(group_runs([tmp_path / "full"])))
    videos = [[row["videos"] for row in stage["eval"]] for stage in full["stages"]]  # one per learned skill
    assert [[len(v) for v in stage] for stage in videos] == [[1], [1, 1]]
    assert videos[1][0][0].startswith("videos/stage_02_door-open/reach_episode0_")
    assert all((tmp_path / "full" / v[0]).stat().st_size > 1000 for stage in videos for v in stage)

    def kill_after_first(stage):
        if stage == 0:
            raise SimulatedKillError

    with pytest.raises(SimulatedKillError):
        SACTrainer(tiny_config(tmp_path / "killed"), after_stage=kill_after_first).run()
    assert not (tmp_path / "killed" / "results.json").exists()
    resumed = SACTrainer(tiny_config(tmp_path / "killed", resume=True)).run()
    for key in ("success_matrix", "metrics"):
        assert resumed[key] == full[key], key
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}  # noqa: E731
    assert strip(resumed["stages"][1]["sleep"]) == strip(full["stages"][1]["sleep"])
    assert resumed["stages"][1]["wake"]["final_train_reward"] == full["stages"][1]["wake"]["final_train_reward"]


def test_output_dir_safety_and_loud_failures(tmp_path):
    out = tmp_path / "run"
    cfg = tiny_config(out, skills=["reach-v3"], eval=EvalConfig(episodes=1))
    SACTrainer(cfg).run()
    with pytest.raises(FileExistsError, match="--resume"):
        SACTrainer(tiny_config(out, skills=["reach-v3"])).run()
    with pytest.raises(SettingsMismatchError, match=r"settings_fingerprint.json: .*seed: 3 -> 4"):
        SACTrainer(tiny_config(out, skills=["reach-v3"], seed=4, resume=True)).run()
    # a killed two-skill run resumes from stage 1's checkpoint: a truncated one is refused naming it
    killed = tmp_path / "killed"

    def kill(stage):
        raise SimulatedKillError

    with pytest.raises(SimulatedKillError):
        SACTrainer(tiny_config(killed, eval=EvalConfig(episodes=1)), after_stage=kill).run()
    ckpt = killed / "stages" / "01_reach" / "wake" / "agent.safetensors"
    ckpt.write_bytes(ckpt.read_bytes()[:-10])
    with pytest.raises(CorruptFileError, match="01_reach/wake/agent.safetensors"):
        SACTrainer(tiny_config(killed, eval=EvalConfig(episodes=1), resume=True)).run()
    SACTrainer(tiny_config(out, skills=["reach-v3"], eval=EvalConfig(episodes=1), overwrite=True)).run()
    assert json.loads((out / "results.json").read_text())["skills"] == ["reach"]
    with pytest.raises(ValueError, match="exclude each other"):
        tiny_config(out, resume=True, overwrite=True)


@pytest.mark.parametrize("name", ["sac_mt5_paper.json", "sac_mt5_cpu.json"])
def test_shipped_configs_parse(name):
    cfg = draccus.parse(RLTrainConfig, config_path=CONFIGS / name, args=["--seed=7"])
    assert cfg.seed == 7 and cfg.stream_skills[0] == "reach-v3"
    assert cfg.sleep.fw_iterations == 50 and cfg.sleep.max_iterations == 4000 and cfg.sleep.lr == 5e-4
    assert cfg.excitability.e_min == 0.1 and cfg.excitability.e_max == 5.0
    assert cfg.sac.target_entropy == -2.0 and cfg.sac.hidden_dim == 256


def test_evaluation_is_paired_across_stages_and_after_wake(tmp_path, monkeypatch):
    """Skill i is evaluated on the same Meta-World configurations at stage i, at stage i + 1 and right after its
    wake (common random numbers). With the old per-stage seed (seed_sequence(seed, k, 100 + i)) the reach episodes at
    stage 2 drew different configurations than at stage 1, and this test failed."""
    cfg = tiny_config(tmp_path / "paired", eval=EvalConfig(episodes=6, videos_per_skill=0), max_episode_steps=10)
    trainer = SACTrainer(cfg)
    agent = SACAgent(cfg.sac, cfg.excitability)
    trainer.substrate.agent = agent
    seen: list[tuple[str, int]] = []
    original_reset = SkillEnv.reset

    def recording_reset(self, configuration=None):
        obs = original_reset(self, configuration)
        seen.append((self.skill, self.configuration))
        return obs

    monkeypatch.setattr(SkillEnv, "reset", recording_reset)

    def configurations(run):
        seen.clear()
        rows, _ = run()
        by_skill: dict[str, list[int]] = {}
        for skill, c in seen:
            by_skill.setdefault(skill, []).append(c)
        return rows, by_skill

    rows_1, stage_1 = configurations(lambda: trainer.substrate.evaluate_rows(0, [0]))
    rows_2, stage_2 = configurations(lambda: trainer.substrate.evaluate_rows(1, [0, 1]))
    wake_rows, after_wake_2 = configurations(lambda: trainer.substrate.evaluate_rows(1, [1]))
    assert len(stage_1["reach-v3"]) == 6 and len(set(stage_1["reach-v3"])) > 1
    assert stage_2["reach-v3"] == stage_1["reach-v3"]
    assert after_wake_2["door-open-v3"] == stage_2["door-open-v3"] and "reach-v3" not in after_wake_2
    assert rows_2[0]["configurations"] == stage_1["reach-v3"]
    # Same policy, same configurations: the same numbers, which is why a stage without sleep reuses its stage
    # evaluation as the after-wake one.
    assert wake_rows[-1] == rows_2[-1]
    assert rows_2[0] == rows_1[0]
    # Another run seed draws other configurations.
    other = SACTrainer(tiny_config(tmp_path / "other", seed=4, eval=EvalConfig(episodes=6, videos_per_skill=0),
                                      max_episode_steps=10))
    other.substrate.agent = agent
    _, stage_1_other = configurations(lambda: other.substrate.evaluate_rows(0, [0]))
    assert stage_1_other["reach-v3"] != stage_1["reach-v3"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("uninterrupted") / "full"
    return out, SACTrainer(tiny_config(out, eval=EvalConfig(episodes=2, videos_per_skill=0))).run()


@pytest.mark.parametrize("point", [(1, "wake"), (1, "wake.eval"), (1, "sleep")])
def test_a_kill_inside_a_stage_resumes_to_the_uninterrupted_results(tmp_path, uninterrupted, point):
    """The engine records every phase: a run killed after the wake, the after-wake evaluation or the sleep of
    stage 2 resumes there (nothing is redone) and ends bit-identical to an uninterrupted run."""
    cfg = dict(eval=EvalConfig(episodes=2, videos_per_skill=0))
    full_out, full = uninterrupted

    stop_after(tmp_path / "killed", point, **cfg)
    redone = []
    resumed = SACTrainer(tiny_config(tmp_path / "killed", resume=True, **cfg),
                            after_phase=lambda k, p: redone.append((k, p))).run()
    phases = [(1, p) for p in ("wake", "memory", "wake.eval", "sleep", "sleep.eval")]
    assert redone == phases[phases.index(point) + 1:]
    for key in ("success_matrix", "success_after_own_wake", "metrics"):
        assert resumed[key] == full[key], key
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}  # noqa: E731
    assert strip(resumed["stages"][1]["sleep"]) == strip(full["stages"][1]["sleep"])
    a, _ = load_checked_safetensors(full_out / "stages" / "02_door-open" / "sleep" / "agent.safetensors")
    b, _ = load_checked_safetensors(tmp_path / "killed" / "stages" / "02_door-open" / "sleep" / "agent.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)


def test_a_run_that_stored_its_config_as_config_json_resumes_from_it(tmp_path, uninterrupted):
    """Every run stores train_config.json; a SAC run in the older layout (config.json, no train_config.json) still
    resumes with ``sr-train --config_path=<run>/config.json --resume=true`` to the uninterrupted results."""
    from sr_imitation.cli import parse_args

    cfg = dict(eval=EvalConfig(episodes=2, videos_per_skill=0))
    run = tmp_path / "old"

    stop_after(run, (1, "wake"), **cfg)
    assert (run / "train_config.json").is_file() and not (run / "config.json").exists()
    (run / "train_config.json").rename(run / "config.json")  # the older layout: config.json, no train_config.json
    parsed = parse_args([f"--config_path={run / 'config.json'}", "--resume=true"])
    assert parsed.output_dir == run
    resumed = SACTrainer(parsed).run()
    assert resumed["metrics"] == uninterrupted[1]["metrics"]
    assert not (run / "train_config.json").exists()  # nothing stored at the start is rewritten


def test_extend_from_continues_a_finished_stream_with_its_stages(tmp_path):
    """MT8 from MT5 in miniature: a finished one-skill run is extended by a second skill; stage 1 is imported (its
    evaluation and checkpoint are the source's), only stage 2 runs. Not equal to a two-skill run from scratch: the
    network initialization seed depends on the stream length (seed_sequence(seed, K, 1)), as the paper's MT8 continues
    from MT5's weights rather than re-running them."""
    cfg = dict(eval=EvalConfig(episodes=2, videos_per_skill=0))
    source = SACTrainer(tiny_config(tmp_path / "mt1", skills=["reach-v3"], **cfg)).run()
    ran = []
    extended = SACTrainer(tiny_config(tmp_path / "mt2", extend_from=tmp_path / "mt1", **cfg),
                             after_phase=lambda k, p: ran.append((k, p))).run()
    assert {k for k, _ in ran} == {1} and "sleep" in [p for _, p in ran]
    assert extended["success_matrix"][0][:1] == source["success_matrix"][0]
    assert extended["stages"][0]["eval"] == source["stages"][0]["eval"]
    a, _ = load_checked_safetensors(tmp_path / "mt1" / "stages" / "01_reach" / "wake" / "agent.safetensors")
    b, _ = load_checked_safetensors(tmp_path / "mt2" / "stages" / "01_reach" / "wake" / "agent.safetensors")
    assert all(torch.equal(a[n], b[n]) for n in a)
    with pytest.raises(SettingsMismatchError, match="sac.hidden_dim"):
        SACTrainer(tiny_config(tmp_path / "bad", extend_from=tmp_path / "mt1",
                                  sac=SACConfig(hidden_dim=16, batch_size=16, utd_ratio=0.5, warmup_steps=40,
                                                buffer_size=5000), **cfg)).run()
    assert not (tmp_path / "bad").exists()


def test_an_unknown_skill_is_refused_before_the_first_gradient(tmp_path):
    """``--stream.skills=[reach-v3,door-open-v3,fooo-v3]`` is refused when the trainer is built, naming
    ``stream.skills``, with nothing written (it used to fail after two stages: hours at the real preset)."""
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"^stream.skills: \['fooo-v3'\] are not Meta-World v3 environments"):
        SACTrainer(tiny_config(out, skills=["reach-v3", "fooo-v3"]))
    assert not out.exists()


def test_every_sealed_file_is_verified_before_a_resume_writes(tmp_path, uninterrupted):
    """A flipped byte in a completed phase's file (the last stage's trajectories and sleep diagnostics used to be
    read only at the report) is refused naming the file before the resume writes anything."""
    from tests.infra.test_fingerprint import tree_state

    cfg = dict(eval=EvalConfig(episodes=2, videos_per_skill=0))
    stopped = tmp_path / "stopped"

    stop_after(stopped, (1, "sleep"), **cfg)
    files = ["stages/01_reach/trajectories.safetensors", "stages/02_door-open/sleep/sleep_diagnostics.json",
             "stages/02_door-open/memory.safetensors", "stages/01_reach/wake/agent.safetensors", "progress.json"]
    for name in files:
        run = tmp_path / name.replace("/", "_")
        shutil.copytree(stopped, run)
        data = bytearray((run / name).read_bytes())
        data[len(data) // 2] ^= 0x01
        (run / name).write_bytes(bytes(data))
        before = tree_state(run)
        with pytest.raises(CorruptFileError, match=re.escape(name)):
            SACTrainer(tiny_config(run, resume=True, **cfg)).run()
        assert tree_state(run) == before, name


def test_a_start_killed_while_writing_train_config_resumes_to_the_uninterrupted_files(tmp_path, uninterrupted,
                                                                                       monkeypatch):
    """Killed inside the atomic write of ``train_config.json`` (its torn temporary file left, the fingerprint
    complete): the resume writes the config from its own (fingerprint-checked) settings, byte-identical to an
    uninterrupted run's, and continues. Before: it finished without one."""
    from sr_imitation.stream import rundir

    cfg = dict(eval=EvalConfig(episodes=2, videos_per_skill=0))
    run, real = tmp_path / "killed", rundir.write_checked_json

    def killed_inside_the_config_write(path, obj):
        if Path(path).name != "train_config.json":
            return real(path, obj)
        (Path(path).parent / ".train_config.json.x1.tmp").write_text('{"output_dir": ".", "se')  # what a kill leaves
        raise SimulatedKillError

    with monkeypatch.context() as patch:
        patch.setattr(rundir, "write_checked_json", killed_inside_the_config_write)
        with pytest.raises(SimulatedKillError):
            SACTrainer(tiny_config(run, **cfg)).run()
    assert sorted(p.name for p in run.iterdir()) == [".train_config.json.x1.tmp", "settings_fingerprint.json"]
    with pytest.raises(SimulatedKillError):  # resumed, and stopped again after its first phase
        SACTrainer(tiny_config(run, resume=True, **cfg),
                   after_phase=lambda k, p: (_ for _ in ()).throw(SimulatedKillError)).run()
    full_out, _ = uninterrupted
    for name in ("train_config.json", "settings_fingerprint.json"):
        assert (run / name).read_bytes() == (full_out / name).read_bytes(), name
    assert not list(run.glob(".*.tmp"))
