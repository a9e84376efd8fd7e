"""``sr-sleep``: consolidate a deployed ACT-SR policy offline from saved memory files.

(a) on an ``sr-train`` run's memories (and on stock-format checkpoints trained on two datasets of their own) it
lowers the summed memory loss and writes the tables and a checkpoint that ``lerobot-eval``'s loader loads; (b) with
the run's settings, its anchor and its seed it reproduces the run's own sleep bit for bit; (c) a bad input is one
line naming it, and nothing is written.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_policy, make_pre_post_processors
from safetensors.torch import load_file

from lerobot_policy_act_sr.actor_memory import ActorMemory
from lerobot_policy_act_sr.modeling_act_sr import MEMORY_FILE
from sr_imitation.core.memory import load_memory
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.io import CorruptFileError, read_checked_json, verify_manifest
from sr_imitation.stream.substrate import phase_seed
from sr_imitation.substrates.act.cli import checkpoint_stream, sleep_main
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.evaluate import episode_positions
from sr_imitation.substrates.act.offline_sleep import (
    AnchorConfig,
    OfflineSleepConfig,
    PolicyPathConfig,
    SleepEvalConfig,
    load_actor_memory,
    load_policy,
    run_offline_sleep,
)
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.substrates.act.conftest import SKILLS
from tests.substrates.act.helpers import FakeNeedleEnv, fake_env_factory, tiny_policy, tiny_stream_config

SEED = 7  # tiny_stream_config's run seed
# The gate of Eq. 2 decides (a finite tau), and the anchor is strong enough to change the result.
RUN_SLEEP = {"lr": 1e-3, "max_iterations": 5, "early_stop_window": 5, "anchor_tau": 1e6, "anchor_strength": 1.0}


def _stage(run: Path, k: int, phase: str) -> Path:
    return run / f"skill_{k}_{SKILLS[k - 1]}" / phase / "pretrained_model"


def _memories(run: Path, k: int) -> list[Path]:
    return [run / "memories" / f"skill_{i}_{SKILLS[i - 1]}.safetensors" for i in range(1, k + 1)]


@pytest.fixture(scope="module")
def run(state_datasets, tmp_path_factory) -> tuple[Path, SurgicAISleepConfig]:
    """A finished three-skill sr-train run (state-only ACT-SR, SR with sleeps after skills 2 and 3)."""
    out = tmp_path_factory.mktemp("offline_sleep") / "run"
    cfg = tiny_stream_config(state_datasets, out, SKILLS, use_images=False, sleep=RUN_SLEEP)
    ACTTrainer(cfg, fake_env_factory).run()
    return out, cfg.sleep


def test_the_runs_memories_are_evaluated_in_one_policy_call(run):
    """The memories sr-train writes each name their own checkpoint; that name must not split them: wake distillation
    and the sleep's joint forward evaluate them all in one forward pass (before 2026-11-27 it took one pass each)."""
    from sr_imitation.core.memory import per_memory_losses

    out, _ = run
    memories = [load_memory(p) for p in _memories(out, 3)]
    assert len({m.config["snapshot"] for m in memories}) == 3
    calls = []

    def counted(obs):
        calls.append(len(next(iter(obs.values()))))
        return torch.zeros(calls[-1], *memories[0].tensors["target"].shape[1:])

    gen = torch.Generator().manual_seed(0)
    per_memory_losses(memories, counted, [m.sample(4, gen) for m in memories])
    assert calls == [12]


def _same_weights(a: Path, b: Path) -> bool:
    x, y = load_file(str(a / "model.safetensors")), load_file(str(b / "model.safetensors"))
    return x.keys() == y.keys() and all(torch.equal(x[n], y[n]) for n in x)


# -- (b) the stream's sleep, repeated ---------------------------------------------------------------------------
@pytest.mark.parametrize("k", [2, 3])
def test_sleeping_a_runs_wake_checkpoint_with_its_anchor_and_seed_gives_the_runs_own_sleep(run, tmp_path, k):
    out, sleep = run
    anchor = _stage(out, k - 1, "wake" if k == 2 else "sleep")  # theta_{k-1}^sleep: stage 1 has no sleep
    cfg = OfflineSleepConfig(policy=PolicyPathConfig(path=_stage(out, k, "wake")), memories=_memories(out, k),
                             anchor=AnchorConfig(path=anchor), final_skill=k == len(SKILLS),
                             sleep=dataclasses.replace(sleep, seed=phase_seed("decimal", SEED, k - 1, "sleep")),
                             output_dir=tmp_path / "slept", progress=False)
    record = run_offline_sleep(cfg)
    assert record["gate_snapshots"] == k - 1 and record["sleep"]["anchor_lambda"] == 1.0
    assert [m["targets"] for m in record["memories"]] == ["as stored"] * k  # one set of stream statistics
    assert _same_weights(tmp_path / "slept" / "pretrained_model", _stage(out, k, "sleep"))  # every tensor, exactly
    ours = json.loads((tmp_path / "slept" / "sleep_diagnostics.json").read_text())
    theirs = json.loads((_stage(out, k, "sleep").parent / "sleep_diagnostics.json").read_text())
    assert ours == theirs  # every iteration's losses, Nash weights, gradient norms, gate distances

    if k == len(SKILLS):  # the anchor matters: the default (the deployed policy) gives another consolidation
        other = run_offline_sleep(dataclasses.replace(cfg, anchor=AnchorConfig(), output_dir=tmp_path / "default"))
        assert other["anchor"] == "the deployed policy"
        assert not _same_weights(tmp_path / "default" / "pretrained_model", _stage(out, k, "sleep"))


# -- (a) the command ---------------------------------------------------------------------------------------------
def _loads_as_lerobot_eval_does(path: Path):
    """``lerobot-eval --policy.path``'s loader: config, policy class from the registry, the saved processors."""
    config = PreTrainedConfig.from_pretrained(path)
    config.device = "cpu"
    policy = get_policy_class(config.type).from_pretrained(path, config=config)
    pre, post = make_pre_post_processors(config, pretrained_path=str(path),
                                         preprocessor_overrides={"device_processor": {"device": "cpu"}})
    return config, policy, pre, post


def test_sr_sleep_lowers_the_summed_memory_loss_and_writes_a_checkpoint_lerobot_eval_loads(run, tmp_path, capsys):
    out, _ = run
    target = tmp_path / "slept"
    memories = ",".join(str(p) for p in _memories(out, 2))
    record = sleep_main([f"--policy.path={_stage(out, 2, 'wake')}", f"--memories=[{memories}]",
                         f"--output_dir={target}", "--sleep.lr=1e-3", "--sleep.max_iterations=20",
                         "--sleep.early_stop_window=20", "--sleep.batch_size=8", "--progress=false"])
    printed = capsys.readouterr().out
    assert "| **sum** |" in printed and str(target / "pretrained_model") in printed
    # The table: M_2 is the deployed policy's own memory (zero loss before), M_1 was partly forgotten.
    losses = record["summed_loss"]
    assert record["memories"][1]["loss_before"] == 0.0 and record["memories"][0]["loss_before"] > 0
    assert losses["after"] <= losses["before"], losses
    assert record["anchor"] == "the deployed policy" and record["sleep"]["stop_iteration"] == 20
    assert read_checked_json(target / "sleep.json") == record
    md = (target / "sleep.md").read_text()
    assert "| 1 | `skill_1_approach.safetensors` | approach | 16 | as stored |" in md
    assert "Success: not evaluated" in md
    verify_manifest(target)  # checkpoint, tables and diagnostics sealed
    # The consolidated policy loads as lerobot-eval loads it and acts; the memory losses are its own.
    config, policy, pre, post = _loads_as_lerobot_eval_does(target / "pretrained_model")
    assert config.type == "act_sr"
    action = post(policy.select_action(pre({"observation.state": torch.zeros(1, 6)})))
    assert action.shape == (1, 7) and torch.isfinite(action).all()
    loaded = load_policy(target / "pretrained_model", "cpu")
    for entry in record["memories"]:
        memory = load_memory(entry["file"])
        batch = {key: memory.tensors[key] for key in memory.buffer_keys}
        with torch.no_grad():
            assert float(memory.loss(loaded.policy.memory_chunk, batch)) == pytest.approx(entry["loss_after"],
                                                                                          rel=1e-5)
    # Refused a second time, replaced with --overwrite=true.
    args = [f"--policy.path={_stage(out, 2, 'wake')}", f"--memories=[{memories}]", f"--output_dir={target}",
            "--sleep.max_iterations=2", "--progress=false"]
    with pytest.raises(FileExistsError, match="already exists; pass --overwrite=true"):
        sleep_main(args)
    assert sleep_main([*args, "--overwrite=true"])["sleep"]["stop_iteration"] == 2
    assert read_checked_json(target / "sleep.json")["sleep"]["stop_iteration"] == 2
    # --overwrite=true never removes what sr-sleep did not write: a user's folder, or an output with a file added.
    mine = tmp_path / "my_project"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    (target / "analysis.ipynb").write_text("{}")
    for folder, why in ((mine, "it holds no sleep.json, so it is not an sr-sleep output"),
                        (target, "it holds analysis.ipynb, which sr-sleep does not write")):
        args[2] = f"--output_dir={folder}"
        with pytest.raises(ValueError, match=rf"{folder}: --overwrite=true refused: {why}; .*nothing was removed"):
            sleep_main([*args, "--overwrite=true"])
    assert (mine / "notes.txt").read_text() == "precious" and (target / "analysis.ipynb").is_file()
    verify_manifest(target)  # the earlier output untouched


def test_success_before_and_after_where_an_environment_is_given(run, tmp_path):
    out, _ = run
    cfg = OfflineSleepConfig(policy=PolicyPathConfig(path=_stage(out, 2, "wake")), memories=_memories(out, 2),
                             sleep=SurgicAISleepConfig(max_iterations=3, batch_size=4),
                             eval=SleepEvalConfig(skills=["approach", "place"], episodes=2, seeds=[0], max_steps=5),
                             output_dir=tmp_path / "slept", progress=False)
    record = run_offline_sleep(cfg, make_env=fake_env_factory)
    assert set(record["success"]) == {"approach", "place"}
    for result in record["success"].values():
        assert 0.0 <= result["before"] <= 1.0 and 0.0 <= result["after"] <= 1.0
        assert len(result["videos"]) == 2 and all((tmp_path / "slept" / v).is_file() for v in result["videos"])
    assert "| approach |" in (tmp_path / "slept" / "sleep.md").read_text()


# -- stock lerobot-train checkpoints: two datasets, two sets of statistics ----------------------------------------
def _stock_checkpoint(dataset_root: Path, skill: str, directory: Path) -> Path:
    """What ``lerobot-train --policy.type=act_sr --policy.sleep=true`` saves (tests/substrates/act/test_policy_sleep.py
    runs the real command): a policy trained a few steps on one dataset, its processors with that dataset's
    statistics, and the skill's memory beside them."""
    dataset = LeRobotDataset(f"local/sr_needle_{skill}", root=dataset_root / skill,
                             delta_timestamps={"action": [i / 10 for i in range(4)]})
    torch.manual_seed(0)
    policy = make_policy(tiny_policy(sleep=True, sleep_memory_size=8), ds_meta=dataset.meta)
    pre, post = make_pre_post_processors(policy.config, dataset_stats=dataset.meta.stats)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    policy.train()
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, shuffle=True,
                                         generator=torch.Generator().manual_seed(0))
    for _, batch in zip(range(3), loader, strict=False):
        loss, _ = policy.forward(pre(batch))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    policy.save_pretrained(directory)
    pre.save_pretrained(directory)
    post.save_pretrained(directory)
    return directory


def test_stock_memories_of_two_datasets_are_consolidated_in_the_deployed_policys_action_space(image_datasets,
                                                                                            tmp_path):
    approach = _stock_checkpoint(image_datasets, "approach", tmp_path / "approach" / "pretrained_model")
    place = _stock_checkpoint(image_datasets, "place", tmp_path / "place" / "pretrained_model")
    cfg = OfflineSleepConfig(policy=PolicyPathConfig(path=place), memories=[approach / MEMORY_FILE,
                                                                            place / MEMORY_FILE],
                             sleep=SurgicAISleepConfig(lr=1e-3, max_iterations=10, batch_size=4,
                                                       early_stop_window=10),
                             output_dir=tmp_path / "slept", progress=False)
    record = run_offline_sleep(cfg)
    assert [m["targets"] for m in record["memories"]] == ["re-expressed", "as stored"]
    assert record["gate_snapshots"] == 1  # approach's snapshot is its own checkpoint (".")
    assert record["memories"][1]["loss_before"] < 1e-10  # the deployed policy is place's snapshot
    assert record["summed_loss"]["after"] <= record["summed_loss"]["before"]
    # Approach's targets, unnormalized with approach's statistics, normalized with place's: the same raw actions.
    _, _, _, post_a = _loads_as_lerobot_eval_does(approach)
    _, _, pre_p, post_p = _loads_as_lerobot_eval_does(place)
    stored = load_memory(approach / MEMORY_FILE).tensors["target"]
    loaded = load_policy(place, "cpu")
    mapped = load_actor_memory(approach / MEMORY_FILE, loaded).memory.tensors["target"]
    assert not torch.allclose(mapped, stored)
    assert torch.allclose(post_p(mapped.reshape(-1, 7)), post_a(stored.reshape(-1, 7)), atol=1e-5)
    _loads_as_lerobot_eval_does(tmp_path / "slept" / "pretrained_model")


# -- (c) bad inputs: one line naming them, nothing written -------------------------------------------------------
def _one_line_error(capsys, args: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        run_cli("sr-sleep", sleep_main, args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sr-sleep: error: ") and "\n" not in err, err
    return err


def test_bad_inputs_are_one_line_naming_the_file_and_nothing_is_written(run, tmp_path, capsys):
    out, _ = run
    target = tmp_path / "slept"
    policy = _stage(out, 2, "wake")
    m1, m2 = _memories(out, 2)

    def nothing_written() -> None:
        assert not target.exists() and not any(p.name.startswith(".slept") for p in tmp_path.iterdir())

    def refused(memories: list[Path], **settings) -> str:
        """The command's one line (through run_cli, as the console script reports it)."""
        args = [f"--{key}={value}" for key, value in {"policy.path": policy, "output_dir": target,
                                                      "progress": "false", **settings}.items()]
        err = _one_line_error(capsys, [*args, f"--memories=[{','.join(map(str, memories))}]"])
        nothing_written()
        return err

    def raised(memories: list[Path], **settings) -> str:
        """The error the command reports (run_cli prints its message as one line), raised by the library call."""
        fields = {"policy": PolicyPathConfig(path=policy), "output_dir": target, "progress": False, **settings}
        with pytest.raises((ValueError, FileNotFoundError, CorruptFileError)) as info:
            run_offline_sleep(OfflineSleepConfig(memories=memories, **fields))
        nothing_written()
        return str(info.value)

    missing = tmp_path / "nowhere.safetensors"
    assert f"{missing}: no such file" in refused([m1, missing])
    assert "is not a LeRobot pretrained_model directory" in raised([m1], policy=PolicyPathConfig(path=tmp_path))
    # Memories of other policies: with a camera this state-only policy has not, with another state, with other
    # action chunks.
    memory = load_memory(m2)

    def other(name: str, **tensors) -> Path:
        path = tmp_path / f"{name}.safetensors"
        ActorMemory(memory.skill, {**memory.tensors, **tensors}, dict(memory.config)).save(path)
        return path

    camera = other("camera", **{"input.observation.images.wrist": torch.zeros(16, 3, 16, 16, dtype=torch.uint8)})
    err = refused([m1, camera])
    assert f"{camera}: memory observations" in err and "are not the policy's inputs" in err
    state = other("state", **{"input.observation.state": torch.zeros(16, 5)})
    assert f"{state}: memory observation 'observation.state' has shape (5,), the policy takes (6,)" in raised([state])
    short = other("short", target=memory.tensors["target"][:, :2])
    assert f"{short}: memory action chunks are (2, 7)" in raised([m1, short])
    # A damaged file.
    damaged = tmp_path / "damaged.safetensors"
    damaged.write_bytes(m1.read_bytes()[:-20])
    assert str(damaged) in raised([damaged, m2])
    # The gate needs M_1's wake snapshot, which a copied memory file has not beside it.
    copied = tmp_path / "copies" / "m1.safetensors"
    copied.parent.mkdir()
    copied.write_bytes(m1.read_bytes())
    err = raised([copied, m2], sleep=SurgicAISleepConfig(anchor_tau=10.0))
    assert f"{copied}: the gate of Eq. 2" in err and "--sleep.anchor_tau=null" in err
    # Settings that would do nothing, refused when the command line is read.
    assert "sleep.enabled=false" in refused([m1, m2], **{"sleep.enabled": "false"})
    with pytest.raises(ValueError, match="eval.episodes set but eval.skills is empty"):
        OfflineSleepConfig(policy=PolicyPathConfig(path=policy), memories=[m1], eval=SleepEvalConfig(episodes=3))
    with pytest.raises(ValueError, match="is given twice"):
        OfflineSleepConfig(policy=PolicyPathConfig(path=policy), memories=[m1, m1])
    # An output directory holding an input.
    assert f"output_dir {out} holds the input" in raised([m1, m2], output_dir=out, overwrite=True)
    assert (out / "results.json").is_file()


def test_the_console_script_answers_a_missing_memory_in_one_line(run, tmp_path):
    out, _ = run
    exe = Path(sys.executable).parent / "sr-sleep"
    assert exe.exists(), f"sr-sleep is not installed next to {sys.executable} (pip install -e .)"
    missing = tmp_path / "nowhere.safetensors"
    proc = subprocess.run([str(exe), f"--policy.path={_stage(out, 2, 'wake')}", f"--memories=[{missing}]",
                           f"--output_dir={tmp_path / 'slept'}"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip() == (f"sr-sleep: error: {missing}: no such file (--debug shows the traceback)")
    assert not (tmp_path / "slept").exists()


def test_memories_out_of_skill_order_are_refused_naming_the_order(run, tmp_path, capsys):
    """Newest-first memories are refused in one line naming the order to give, by the stages the memories record
    (their snapshots' ``skill_<k>_...``) or, for memories that record none, by the policy's run's skill order.
    Before: accepted, and slept with the newest skill as M_1."""
    out, _ = run
    policy, (m1, m2) = _stage(out, 2, "wake"), _memories(out, 2)
    args = [f"--policy.path={policy}", f"--output_dir={tmp_path / 'slept'}", "--progress=false"]
    err = _one_line_error(capsys, [*args, f"--memories=[{m2},{m1}]"])
    assert "not in skill order by their snapshots' stages" in err and f"--memories=[{m1},{m2}]" in err
    # memories without a stage of their own (as stock lerobot-train writes them): the policy's run decides
    unstaged = []
    for path in (m1, m2):
        memory = load_memory(path)
        unstaged.append(tmp_path / path.name)
        ActorMemory(memory.skill, dict(memory.tensors), {**memory.config, "snapshot": "."}).save(unstaged[-1])
    err = _one_line_error(capsys, [*args, f"--memories=[{unstaged[1]},{unstaged[0]}]"])
    assert f"not in skill order by the skill order of {out.resolve() / 'train_config.json'}" in err
    assert f"--memories=[{unstaged[0]},{unstaged[1]}]" in err and not (tmp_path / "slept").exists()


def test_the_sleep_logs_its_progress_with_the_time_left(caplog):
    """sr-sleep's default 1000 iterations took ~10 min for a user with no estimate: a line every tenth of the budget
    says how far it is, the time spent and at most how long the rest takes at this pace."""
    from sr_imitation.core.sleep import SleepConfig
    from sr_imitation.substrates.act.offline_sleep import _progress_logger

    ticks = iter([0.0, 30.0, 60.0])  # start, then the clock at iterations 100 and 200
    log = _progress_logger(SleepConfig(max_iterations=1000), clock=lambda: next(ticks))
    with caplog.at_level("INFO", logger="sr_imitation.substrates.act.offline_sleep"):
        for it in range(200):
            log(it, {"objective": 0.5, "memory_losses": [0.25, 0.125]})
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["sleep iteration 100/1000 (10%), 30s elapsed, at most ~4m30s left: objective 0.5, memory "
                     "losses [0.25, 0.125]",
                     "sleep iteration 200/1000 (20%), 1m00s elapsed, at most ~4m00s left: objective 0.5, memory "
                     "losses [0.25, 0.125]"]


# -- the run's own episodes in any stream order ----------------------------------------------------------------------
class _RecordingEnv(FakeNeedleEnv):
    """The fake environment, noting every reset seed under its skill."""

    seeds: dict[str, set[int]] = {}

    def reset(self, *, seed=None, options=None):
        type(self).seeds.setdefault(self.skill, set()).add(seed)
        return super().reset(seed=seed, options=options)


def test_sr_sleep_and_sr_eval_draw_the_run_s_own_episodes_in_a_non_needle_order(state_datasets, tmp_path):
    """A run in the order place -> approach (not the needle's approach -> place): sr-sleep's evaluation before and after
    the sleep resets each skill with exactly the seeds the run evaluated it with (each skill's position in the
    memories' skill order), and sr-eval finds that order in the checkpoint. Before 2026-12-07 both took a needle
    skill's place in the needle's own order, so in another order they drew other episodes than the run."""
    order = ["place", "approach"]
    cfg = tiny_stream_config(state_datasets, tmp_path / "run", order, use_images=False, sleep=RUN_SLEEP)
    _RecordingEnv.seeds = {}
    ACTTrainer(cfg, lambda skill, render: _RecordingEnv(skill, render)).run()
    run_seeds, _RecordingEnv.seeds = _RecordingEnv.seeds, {}
    wake = tmp_path / "run" / "skill_2_approach" / "wake" / "pretrained_model"
    memories = [tmp_path / "run" / "memories" / f"skill_{i + 1}_{s}.safetensors" for i, s in enumerate(order)]
    sleep_cfg = OfflineSleepConfig(
        policy=PolicyPathConfig(path=wake), memories=memories,
        sleep=SurgicAISleepConfig(max_iterations=3, batch_size=4),
        eval=SleepEvalConfig(skills=order, episodes=cfg.eval.episodes, seeds=list(cfg.eval.seeds),
                             max_steps=cfg.eval.max_steps, videos_per_skill=0),
        output_dir=tmp_path / "slept", progress=False)
    run_offline_sleep(sleep_cfg, make_env=lambda skill, render: _RecordingEnv(skill, render))
    assert _RecordingEnv.seeds == run_seeds and run_seeds["place"] != run_seeds["approach"]
    assert checkpoint_stream(wake) == order
    assert episode_positions(["approach", "place"], checkpoint_stream(wake)) == [1, 0]
    assert episode_positions(["approach", "place"]) == [0, 1]  # no stream known: the needle's own order
    assert episode_positions(["reach-v3", "insert"], ["reach-v3"]) == [0, 2]
