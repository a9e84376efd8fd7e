"""End to end on the real needle environment: sr-main (record -> stream -> report) and stock lerobot-train."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest
from safetensors.torch import load_file

from sr_imitation.io import read_checked_json, write_checked_json
from sr_imitation.main_job import main as main_job
from sr_imitation.substrates.act.cli import train_main

TINY_POLICY = {
    "type": "act_sr", "device": "cpu", "use_images": False, "dim_model": 32, "n_heads": 2, "dim_feedforward": 64,
    "n_encoder_layers": 1, "n_vae_encoder_layers": 1, "chunk_size": 8, "n_action_steps": 8,
}
TINY_SLEEP = {"max_iterations": 4, "batch_size": 4, "early_stop_window": 2}


@pytest.fixture(scope="module")
def main_job_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("main_job")
    config = {
        "record": {"num_episodes": 2, "root": str(tmp / "datasets"), "image_size": 32},
        "train": {
            "policy": TINY_POLICY,
            "memory": {"buffer_size": 32},
            "sleep": TINY_SLEEP,
            "stream": {"skills": ["approach", "place"]},
            "wake": {"max_epochs": 1, "min_epochs": 1, "batch_size": 8, "max_steps_per_epoch": 2},
            "eval": {"episodes": 1, "seeds": [0], "max_steps": 40, "videos_per_skill": 1,
                     "video_height": 64, "video_width": 64},
            "output_dir": str(tmp / "run"),
            "progress": False,
        },
    }
    path = tmp / "config.json"
    path.write_text(json.dumps(config))
    main_job([f"--config_path={path}"])
    return tmp, path


def _decode(path: Path) -> np.ndarray:
    """All frames of an mp4 as uint8 (T, H, W, 3), decoded with PyAV."""
    with av.open(str(path)) as container:
        return np.stack([frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)])


def _table_row(markdown: str, label: str) -> list[str]:
    rows = [line for line in markdown.splitlines() if line.startswith(f"| {label} |")]
    assert len(rows) == 1, (label, markdown)
    return [cell.strip() for cell in rows[0].strip().strip("|").split("|")][1:]


def _check_results_against_files(run: Path, skills: list[str]) -> dict:
    """results.json and results.md agree with the per-phase eval.json files and with each other."""
    results = json.loads((run / "results.json").read_text())
    n = len(skills)
    final = [run / f"skill_{k + 1}_{s}" / ("sleep" if k else "wake") / "eval.json" for k, s in enumerate(skills)]
    wake = [run / f"skill_{k + 1}_{s}" / "wake" / "eval.json" for k, s in enumerate(skills)]
    expected = [[json.loads(final[k].read_text())[skills[i]]["success"] if i <= k else None for i in range(n)]
                for k in range(n)]
    assert results["success_matrix"] == expected
    assert results["success_after_own_wake"] == [json.loads(wake[i].read_text())[skills[i]]["success"]
                                                 for i in range(n)]
    assert all(0.0 <= x <= 1.0 for row in expected for x in row if x is not None)
    s = results["success_matrix"]
    m = results["metrics"]
    assert set(m) >= {"afsr", "prs", "bwt", "bwt_wake", "spi"}
    # AFSR_k = mean of row k up to the diagonal (Eq. 4); BWT / BWT_wake and PRS for the pair (approach, place).
    assert m["afsr"]["curve"] == pytest.approx([np.mean(s[k][: k + 1]) for k in range(n)])
    assert m["afsr"]["final"] == pytest.approx(np.mean(s[-1]))
    assert m["bwt"]["final"] == pytest.approx(s[1][0] - s[0][0])
    assert m["bwt_wake"]["final"] == pytest.approx(s[1][0] - results["success_after_own_wake"][0])
    assert results["pairs"] == [["approach", "place"]]
    assert m["prs"]["curve"][0] is None and m["prs"]["final"] == pytest.approx(min(s[1][0], s[1][1]))
    assert 0.0 <= m["spi"]["final"] <= 1.0 + 1e-9
    # results.md shows the same numbers.
    md = (run / "results.md").read_text()
    for k, skill in enumerate(skills):
        assert _table_row(md, skill) == [f"{x:.2f}" if x is not None else "" for x in s[k]]
    assert _table_row(md, "right after own wake") == [f"{x:.2f}" for x in results["success_after_own_wake"]]
    assert _table_row(md, "AFSR")[0].startswith(f"{m['afsr']['final']:.3f}")
    assert _table_row(md, "PRS")[0].startswith(f"{m['prs']['final']:.3f}")
    return results


def test_main_job_records_trains_evaluates_and_reports(main_job_run):
    tmp, _ = main_job_run
    run = tmp / "run"
    skills = ["approach", "place"]
    assert (tmp / "datasets" / "approach" / "meta" / "info.json").is_file()
    for skill in skills:
        info = json.loads((tmp / "datasets" / skill / "meta" / "info.json").read_text())
        assert info["total_episodes"] == 2 and info["total_frames"] > 2
    results = _check_results_against_files(run, skills)
    assert results["skills"] == skills and results["config"]["eval"]["seeds"] == [0] and results["eval_units"] == 1
    # One evaluation seed of one episode: every success is 0 or 1.
    assert all(x in (0.0, 1.0) for row in results["success_matrix"] for x in row if x is not None)
    for name in ("metrics.png", "success_matrix.png"):
        assert (run / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    # Rollout videos: one per learned skill and phase, 64 x 64 as configured, one frame per step of the episode
    # (plus the first observation), named after its outcome, and not a still image.
    videos = sorted((run / "videos").rglob("*.mp4"))
    assert len(videos) == 1 + 2 + 2  # wake 1: one skill; wake 2 and sleep 2: two skills each
    for video in videos:
        stage, phase = video.parent.parent.name, video.parent.name
        skill, _, outcome = video.stem.partition("_episode0_")
        record = json.loads((run / stage / phase / "eval.json").read_text())[skill]
        assert str(video.relative_to(run)) in record["videos"]
        assert outcome == ("success" if record["success_per_seed"][0] == 1.0 else "failure"), video
        frames = _decode(video)
        assert frames.shape[1:] == (64, 64, 3), video
        assert len(frames) in (record["episode_lengths"][0], record["episode_lengths"][0] + 1), video
        assert frames.std() > 1.0 and np.abs(frames[-1].astype(int) - frames[0].astype(int)).max() > 0, video
    # The scripted expert's full suture: many frames, and the scene moves.
    expert = _decode(run / "expert_suture.mp4")
    assert len(expert) > 50 and expert.std() > 1.0
    assert np.abs(expert[-1].astype(int) - expert[0].astype(int)).mean() > 1.0


def test_the_report_is_rebuilt_from_the_evaluation_files(main_job_run, tmp_path):
    """Known success numbers written into a copy's eval.json files come out in results.json/.md (via resume)."""
    tmp, _ = main_job_run
    run = tmp_path / "run"
    shutil.copytree(tmp / "run", run)
    doctored = {  # phase -> {skill: success}
        "skill_1_approach/wake": {"approach": 0.5},
        "skill_2_place/wake": {"approach": 0.75, "place": 0.5},
        "skill_2_place/sleep": {"approach": 0.25, "place": 1.0},
    }
    for phase, values in doctored.items():
        path = run / phase / "eval.json"
        record = read_checked_json(path)
        for skill, value in values.items():
            record[skill]["success"], record[skill]["success_per_seed"] = value, [value]
        write_checked_json(path, record)  # re-sealed: an edit without it is refused (test_checked_files)
    train_main([f"--config_path={tmp / 'run' / 'train_config.json'}", f"--output_dir={run}", "--resume=true"])
    results = _check_results_against_files(run, ["approach", "place"])
    assert results["success_matrix"] == [[0.5, None], [0.25, 1.0]]
    assert results["success_after_own_wake"] == [0.5, 0.5]
    m = results["metrics"]
    assert m["afsr"]["curve"] == pytest.approx([0.5, 0.625])
    assert m["bwt"]["final"] == pytest.approx(-0.25) and m["prs"]["final"] == pytest.approx(0.25)
    assert "| AFSR | 0.625 |" in (run / "results.md").read_text()


def test_sr_train_resumes_a_finished_run_without_redoing_work(main_job_run):
    tmp, _ = main_job_run
    run = tmp / "run"
    before = (run / "progress.json").read_text()
    stamp = (run / "skill_2_place" / "sleep" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns
    train_main([f"--config_path={run / 'train_config.json'}", "--resume=true"])
    assert (run / "progress.json").read_text() == before
    assert (run / "skill_2_place" / "sleep" / "pretrained_model" / "model.safetensors").stat().st_mtime_ns == stamp
    # LeRobot's habit: the config beside the newest checkpoint resumes the same run
    train_main([f"--config_path={run / 'last' / 'pretrained_model' / 'train_config.json'}", "--resume=true"])
    assert (run / "progress.json").read_text() == before
    assert not (run / "last" / "pretrained_model" / "progress.json").exists()  # nothing written into the checkpoint


def test_checkpoints_carry_the_train_config_and_last_points_at_the_newest_consolidated_policy(main_job_run):
    """LeRobot keeps ``train_config.json`` in each ``pretrained_model/`` and a ``last`` pointer;
    so do we (the pointer is relative, so a moved run keeps it; each copy is covered by its checkpoint's manifest)."""
    from sr_imitation.io import verify_manifest

    tmp, _ = main_job_run
    run = tmp / "run"
    assert (run / "last").is_symlink() and os.readlink(run / "last") == os.path.join("skill_2_place", "sleep")
    stored = json.loads((run / "train_config.json").read_text())
    checkpoints = sorted(run.glob("skill_*/*/pretrained_model"))
    assert len(checkpoints) == 3  # wake 1, wake 2, sleep 2 (no sleep after the first skill)
    for pretrained in checkpoints:
        assert json.loads((pretrained / "train_config.json").read_text()) == stored
        assert "pretrained_model/train_config.json" in json.loads(
            (pretrained.parent / "checksums.json").read_text())["files"]
        verify_manifest(pretrained.parent)


def test_sr_train_refuses_to_overwrite_an_existing_run(main_job_run):
    tmp, _ = main_job_run
    with pytest.raises(FileExistsError, match="--resume=true"):
        train_main([f"--config_path={tmp / 'run' / 'train_config.json'}"])


@pytest.mark.slow
def test_stock_lerobot_train_finds_act_sr(main_job_run, tmp_path):
    """Stock lerobot-train (a real subprocess) makes act_sr from its plugin. Without --policy.sleep the policy keeps
    no reservoir and writes no memory; --policy.use_images=false gives a state-only model there too (it used to be
    stored as false while the model still took the camera: 11.2M parameters instead of 25k). The camera is used by
    default: the stock route's first run checks it (tests/substrates/act/test_sleep_statistics.py)."""
    tmp, _ = main_job_run
    exe = Path(sys.executable).parent / "lerobot-train"
    if not exe.exists():
        pytest.fail(f"lerobot-train is not installed next to {sys.executable}")
    out = tmp_path / "lerobot_out"
    cmd = [str(exe), "--policy.type=act_sr", "--policy.device=cpu", "--policy.use_images=false",
           "--policy.dim_model=32", "--policy.n_heads=2", "--policy.dim_feedforward=64",
           "--policy.n_encoder_layers=1", "--policy.n_vae_encoder_layers=1", "--policy.chunk_size=8",
           "--policy.n_action_steps=8", "--dataset.repo_id=local/sr_needle_approach",
           f"--dataset.root={tmp / 'datasets' / 'approach'}", "--dataset.video_backend=pyav", "--steps=2",
           "--batch_size=2", "--num_workers=0", "--env_eval_freq=0", "--save_freq=2", "--wandb.enable=false",
           f"--output_dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    pretrained = next(out.rglob("pretrained_model/config.json")).parent
    config = json.loads((pretrained / "config.json").read_text())
    assert config["type"] == "act_sr" and config["sleep"] is None
    assert not list(out.rglob("memory.safetensors"))
    assert set(config["input_features"]) == {"observation.state", "observation.environment_state"}
    weights = load_file(str(pretrained / "model.safetensors"))
    assert not any("backbone" in name for name in weights)


@pytest.mark.slow
def test_stock_lerobot_eval_evaluates_a_consolidated_checkpoint(main_job_run, tmp_path):
    """The workflow's last step as a real subprocess: stock ``lerobot-eval`` loads a consolidated (sleep)
    checkpoint of the stream and evaluates it in the needle env this package registers."""
    tmp, _ = main_job_run
    exe = Path(sys.executable).parent / "lerobot-eval"
    checkpoint = tmp / "run" / "last" / "pretrained_model"  # the newest consolidated policy, as LeRobot names it
    out = tmp_path / "eval"
    cmd = [str(exe), f"--policy.path={checkpoint}", "--env.type=needle", "--env.task=place",
           "--env.episode_length=20", "--eval.n_episodes=1", "--eval.batch_size=1", "--policy.device=cpu",
           f"--output_dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads(next(out.rglob("eval_info.json")).read_text())
    assert "overall" in info or "per_task" in info or "aggregated" in info, sorted(info)


def test_sr_eval_evaluates_a_checkpoint_with_videos(main_job_run, tmp_path):
    from sr_imitation.substrates.act.cli import eval_main

    tmp, _ = main_job_run
    checkpoint = tmp / "run" / "skill_2_place" / "sleep" / "pretrained_model"
    eval_main([f"--policy.path={checkpoint}", "--skills=[place]", "--eval.episodes=1", "--eval.seeds=[3]",
               "--eval.max_steps=20", "--eval.video_height=64", "--eval.video_width=64", "--progress=false",
               f"--output_dir={tmp_path}"])
    record = json.loads((tmp_path / "eval.json").read_text())
    assert set(record["results"]) == {"place"} and len(list((tmp_path / "videos").glob("*.mp4"))) == 1
    with pytest.raises(FileNotFoundError, match="no config.json"):
        eval_main([f"--policy.path={tmp_path}", f"--output_dir={tmp_path}"])
    import shutil

    from sr_imitation.io import CorruptFileError

    copy = tmp_path / "copy"
    shutil.copytree(checkpoint.parent, copy)  # a sealed checkpoint with one weight byte flipped
    weights = copy / "pretrained_model" / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))
    with pytest.raises(CorruptFileError, match="model.safetensors"):
        eval_main([f"--policy.path={copy / 'pretrained_model'}", f"--output_dir={tmp_path / 'x'}"])


def test_sr_eval_takes_a_run_s_skills_and_settings_and_never_replaces_an_evaluation_unasked(main_job_run, tmp_path):
    """A checkpoint that sr-train wrote is evaluated on its own stream's skills with its run's evaluation settings
    (it used to default to the five needle skills: a Meta-World checkpoint failed on 'approach'), a flag overriding
    one of them; a second evaluation into the same folder is refused before evaluating, unless --overwrite=true (which
    removes that evaluation's files only)."""
    from sr_imitation.substrates.act.cli import eval_main

    tmp, _ = main_job_run
    checkpoint = tmp / "run" / "last" / "pretrained_model"
    out = tmp_path / "own"
    args = [f"--policy.path={checkpoint}", "--eval.seeds=[3,4]", "--progress=false", f"--output_dir={out}"]
    eval_main(args)
    record = json.loads((out / "eval.json").read_text())["results"]
    assert list(record) == ["approach", "place"]  # the run's stream, not the five needle skills
    assert all(len(r["success_per_seed"]) == 2 for r in record.values())  # the flag over the run's seeds [0]
    assert len(list((out / "videos").glob("*.mp4"))) == 2  # the run's videos_per_skill (1 per skill)
    before = (out / "eval.json").read_bytes()
    with pytest.raises(FileExistsError, match=r"own/eval.json: an earlier evaluation is there"):
        eval_main([*args, "--eval.videos_per_skill=0"])
    assert (out / "eval.json").read_bytes() == before and len(list((out / "videos").glob("*.mp4"))) == 2
    (out / "videos" / "mine.txt").write_text("kept")  # not the evaluation's: --overwrite=true leaves it
    eval_main([*args, "--eval.videos_per_skill=0", "--overwrite=true"])
    assert not list((out / "videos").glob("*.mp4")) and (out / "videos" / "mine.txt").read_text() == "kept"


def test_needle_compare_summarizes_variants_over_seeds(main_job_run, tmp_path, monkeypatch):
    from sr_imitation.experiments import needle_compare
    from sr_imitation.experiments.needle_compare import CompareConfig, run_compare

    tmp, config_path = main_job_run
    cfg = CompareConfig(preset=config_path, seeds=[0], variants=["sr_no_anchor", "sequential_bc", "mt_joint"],
                        output_root=tmp_path)
    summary = run_compare(cfg)
    assert set(summary["variants"]) == {"sr_no_anchor", "sequential_bc", "mt_joint"}
    assert summary["baseline"] == "sr_no_anchor" and set(summary["paired"]) == {"sequential_bc", "mt_joint"}
    # five tables, each a header + a row per variant (metrics, per run, final success, after own wake) or per
    # variant paired with the baseline
    assert (tmp_path / "summary.md").read_text().count("\n| ") == 4 + 3 + 4 + 4 + 4
    assert (tmp_path / "summary.png").stat().st_size > 0 and (tmp_path / "dynamics.png").stat().st_size > 0
    assert summary["variants"]["mt_joint"]["oracle"] and summary["variants"]["mt_joint"]["bwt"]["mean"] == 0.0
    assert "| sequential_bc | 0.00 | nothing | - |" in (tmp_path / "memory.md").read_text()
    monkeypatch.setattr(needle_compare, "train_stream", lambda c: pytest.fail(f"{c.output_dir} was re-run"))
    monkeypatch.setattr(needle_compare, "run_mt_joint", lambda c: pytest.fail(f"{c.output_dir} was re-run"))
    assert run_compare(cfg)["variants"].keys() == summary["variants"].keys()  # finished runs are skipped
    # with an archive: finished runs are copied into it, and a new scratch folder summarizes them from there
    archive = tmp_path / "archive"
    run_compare(dataclasses.replace(cfg, archive=archive))
    assert sorted(p.name for p in archive.iterdir()) == ["mt_joint_seed0", "sequential_bc_seed0",
                                                         "sr_no_anchor_seed0"]
    again = run_compare(dataclasses.replace(cfg, archive=archive, output_root=tmp_path / "next"))
    assert again["variants"]["mt_joint"]["runs"] == {"0": str(archive / "mt_joint_seed0")}
    assert again["variants"]["sr_no_anchor"]["afsr"]["per_seed"] == summary["variants"]["sr_no_anchor"]["afsr"][
        "per_seed"]
    saved = json.loads((tmp_path / "summary.json").read_text())
    run = tmp_path / "sr_no_anchor_seed0"
    final = json.loads((run / "results.json").read_text())["metrics"]["afsr"]["final"]
    assert saved["variants"]["sr_no_anchor"]["afsr"]["per_seed"] == [final]
    assert set(saved["variants"]["sr_no_anchor"]["final_success"]) == set(saved["skills"])
    bc = json.loads((tmp_path / "sequential_bc_seed0" / "results.json").read_text())
    assert bc["memory_bytes"] == {} and not any("sleep" in stage for stage in bc["stages"])  # no memories, no sleep
    # The ablation's override reached the run: it slept, without the anchor.
    assert json.loads((run / "train_config.json").read_text())["sleep"]["anchor_strength"] == 0.0
    assert json.loads((run / "progress.json").read_text())["completed"]["2.sleep"]["anchor_lambda"] == 0.0
    with pytest.raises(ValueError, match="variants: unknown"):
        CompareConfig(variants=["sr_typo"])
    grid = needle_compare.run_config(cfg, needle_compare.preset_with_datasets(config_path, []), "ewc_lam100", 3)
    assert (grid.method, grid.method_options, grid.seed) == ("ewc", {"lam": 100.0}, 3)  # EWC's lambda grid
    alone = needle_compare.run_config(cfg, needle_compare.preset_with_datasets(config_path, []), "sr_sleep_only", 3)
    assert alone.sleep.enabled and alone.method == "sr"  # sleep without the wake-time distillation
    assert [alone.policy.distill_weight(k) for k in (1, 2, 3)] == [0.0, 0.0, 0.0]
    assert grid.policy.distill_weight(2) == 1.0  # the preset's policy untouched for the others


def test_sleep_replay_reproduces_the_original_sleep_and_applies_overrides(main_job_run, tmp_path):
    from sr_imitation.experiments.sleep_replay import SleepReplayConfig, replay

    tmp, _ = main_job_run
    run = tmp / "run"
    # The run normalizes with the statistics of the skills seen so far (the default): stage 2's are recomputed from
    # datasets 1-2 in the replay, the policy and memories re-expressed into them as in the original.
    assert json.loads((run / "train_config.json").read_text())["stream"]["stats"] == "seen"
    same = replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "same", progress=False))
    # Same settings, same phase seeds: the replayed sleep is the original one, loss for loss.
    assert same["replay"] == same["original"]
    assert same["replay"]["final_memory_losses"] is not None
    off = replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "off", progress=False),
                 ["--sleep.anchor_strength=0"])
    assert off["original"]["anchor_lambda"] > 0 and off["replay"]["anchor_lambda"] == 0.0
    assert json.loads((tmp_path / "off" / "train_config.json").read_text())["sleep"]["anchor_strength"] == 0.0
    with pytest.raises(ValueError, match="sleep settings only"):
        replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "x", progress=False), ["--seed=3"])
    # The source run is untouched, and an existing replay is not overwritten without the flag.
    assert "2.sleep" in json.loads((run / "progress.json").read_text())["completed"]
    with pytest.raises(FileExistsError, match="--overwrite"):
        replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "off", progress=False))
    # --overwrite replaces a replay, never a folder of other files nor the source run
    replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "off", overwrite=True, progress=False))
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="refused: it holds no settings_fingerprint.json"):
        replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp_path / "mine", overwrite=True, progress=False))
    with pytest.raises(ValueError, match="refused: it holds the input"):
        replay(SleepReplayConfig(run=run, stage=2, output_dir=tmp, overwrite=True, progress=False))
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine" and (run / "progress.json").is_file()
    with pytest.raises(ValueError, match="stage 1 has no sleep"):
        replay(SleepReplayConfig(run=run, stage=1, output_dir=tmp_path / "bad", progress=False))
