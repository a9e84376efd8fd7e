"""Every hint a command prints works when pasted (issue 87 item 4): each suggestion names only flags the command
has, every path in a printed command is shell-quoted, and each is run here from a folder whose path has spaces
and does what it says (resume, overwrite, the dataset viewer). ``--output_dir`` naming a file (or a folder inside
one) is refused up front in one line, before any work.

Before: an interrupted ``sr-record`` said "resume with --resume=true" (it has no such flag); ``sr-eval
--output_dir=<a file>`` evaluated everything, then failed with ``[Errno 20]`` and suggested ``--resume=true``."""

from __future__ import annotations

import errno
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import sr_imitation.substrates.act.cli as cli
from sr_imitation.infra.cli_errors import DISK_FULL_ADVICE, run_cli
from sr_imitation.io import WriteError
from sr_imitation.substrates.act.config import stored_config_dict
from sr_imitation.substrates.act.dataset_identity import dataset_digest
from sr_imitation.substrates.act.trainer import ACTTrainer, train_stream
from tests.act_helpers import fake_env_factory, make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place"]


@pytest.fixture(scope="module")
def spaced(tmp_path_factory) -> Path:
    """A folder whose path has spaces, holding two tiny state-only datasets (``data/``) and a video one
    (``video data/approach``)."""
    os.environ.setdefault("HF_HOME", str(tmp_path_factory.mktemp("hf_home")))
    base = tmp_path_factory.mktemp("hints") / "my runs (copy)"
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(base / "data", skill, i, image=False)
    make_skill_dataset(base / "video data", "approach", 0, video=True)
    return base


@pytest.fixture
def train(spaced, tmp_path, monkeypatch):
    """``sr-train``'s arguments for a tiny stream in ``<tmp>/out dir/run 1``, its environments the fake ones."""
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))
    config = tmp_path / "a config.json"
    cfg = tiny_stream_config(spaced / "data", tmp_path / "unused", SKILLS, use_images=False)
    config.write_text(json.dumps(stored_config_dict(cfg)))
    return [f"--config_path={config}", f"--output_dir={tmp_path / 'out dir' / 'run 1'}"]


def error_of(prog, main, args, capsys, code=2) -> str:
    """The one line ``prog`` prints on stderr for ``args`` (exit status ``code``)."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        run_cli(prog, main, args)
    err = capsys.readouterr().err
    assert exc.value.code == code and err.count("\n") == 1, err
    return err.strip()


def pasted(line: str, marker: str) -> list[str]:
    """The command printed after ``marker`` in ``line``, split as a shell splits it when pasted."""
    assert marker in line, line
    return shlex.split(line.split(marker, 1)[1])


def _done(run: Path) -> bool:
    return (run / "results.json").is_file()


def test_an_interrupted_sr_train_prints_the_command_that_resumes_it(train, tmp_path, monkeypatch, capsys):
    calls = []

    def interrupt(self, k, phase):
        calls.append((k, phase))
        raise KeyboardInterrupt

    monkeypatch.setattr(ACTTrainer, "on_phase", interrupt)
    line = error_of("sr-train", cli.train_main, [*train, "--overwrite=true"], capsys, code=130)
    argv = pasted(line, "sr-train: interrupted; continue with: ")
    assert argv[0] == "sr-train" and argv[-1] == "--resume=true" and "--overwrite=true" not in argv
    monkeypatch.undo()
    monkeypatch.setattr(cli, "train_stream", lambda cfg: train_stream(cfg, fake_env_factory))
    run_cli("sr-train", cli.train_main, argv[1:])  # resumes and finishes
    run = tmp_path / "out dir" / "run 1"
    assert _done(run) and len(calls) == 1
    assert json.loads((run / "progress.json").read_text())["completed"]  # resumed, not restarted elsewhere


def test_an_sr_train_interrupted_before_its_run_exists_says_to_run_it_again(train, tmp_path, monkeypatch, capsys):
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("sr_imitation.substrates.act.trainer.stream_inputs", interrupt)  # hashing the datasets
    line = error_of("sr-train", cli.train_main, train, capsys, code=130)
    assert "--resume" not in line
    assert pasted(line, "sr-train: interrupted; run it again: ") == ["sr-train", *train]


def test_the_exists_hint_names_flags_that_do_what_they_say(train, tmp_path, capsys):
    run = tmp_path / "out dir" / "run 1"
    run_cli("sr-train", cli.train_main, train)
    first = (run / "log.jsonl").stat().st_mtime_ns
    line = error_of("sr-train", cli.train_main, train, capsys)
    assert "pass --resume=true to continue it or --overwrite=true to replace it" in line
    run_cli("sr-train", cli.train_main, [*train, "--resume=true"])  # continues: nothing left to do, nothing redone
    assert (run / "log.jsonl").stat().st_mtime_ns == first
    run_cli("sr-train", cli.train_main, [*train, "--overwrite=true"])  # replaces it
    assert _done(run) and (run / "log.jsonl").stat().st_mtime_ns != first


def test_a_folder_that_holds_no_run_gets_no_resume_hint(train, tmp_path, capsys):
    run = tmp_path / "out dir" / "run 1"
    run.mkdir(parents=True)
    (run / "notes.txt").write_text("mine")
    line = error_of("sr-train", cli.train_main, train, capsys)
    assert "--resume" not in line and "--overwrite" not in line and "choose another output_dir" in line
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]


def test_an_output_dir_in_or_at_a_file_is_refused_up_front(train, tmp_path, monkeypatch, capsys):
    afile = tmp_path / "a file"
    afile.write_text("x")
    line = error_of("sr-train", cli.train_main, [*train[:1], f"--output_dir={afile / 'run'}"], capsys)
    assert f"{afile / 'run'}: lies in {afile}, which is a file, not a folder" in line and "--resume" not in line
    monkeypatch.setattr(cli, "evaluate_checkpoint", lambda cfg: pytest.fail("evaluated"))
    line = error_of("sr-eval", cli.eval_main, [f"--policy.path={tmp_path / 'model'}", f"--output_dir={afile}"], capsys)
    assert f"{afile}: is a file, not a folder" in line and "--resume" not in line
    assert afile.read_text() == "x"


@pytest.mark.parametrize("prog", ["sr-record", "sr-eval", "sr-sleep", "sr-sac-sleep"])
def test_commands_without_a_resume_flag_suggest_none(prog, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    assert error_of(prog, interrupted, [], capsys, code=130) == f"{prog}: interrupted"

    def disk_full(args):
        raise WriteError("/x/eval.json", OSError(errno.ENOSPC, "No space left on device"))

    line = error_of(prog, disk_full, [], capsys)
    assert "--resume" not in line and "nothing half-written was left" in line

    def third_party_disk_full(args):
        raise OSError(errno.ENOSPC, "No space left on device", "/x/video.mp4")

    line = error_of(prog, third_party_disk_full, [], capsys)
    assert "--resume" not in line and line.startswith(f"{prog}: error: /x/video.mp4: cannot write")


def test_sr_main_is_told_its_own_flag_names(spaced, tmp_path, capsys):
    from sr_imitation.main_job import main

    repo = Path(__file__).resolve().parents[1]
    line = error_of("sr-main", main, [f"--config_path={repo / 'configs' / 'needle_cpu.json'}",
                                      f"--train.output_dir={tmp_path / 'r'}", "--train.resume=true",
                                      "--train.overwrite=true"], capsys)
    assert "--train.resume and --train.overwrite exclude each other" in line
    assert DISK_FULL_ADVICE.startswith("free space, then continue with --resume=true")

    def disk_full(args):
        from sr_imitation.infra.cli_errors import note_run_started

        note_run_started(tmp_path / "r")
        raise WriteError("/x/log.jsonl", OSError(errno.ENOSPC, "No space left on device"))

    line = error_of("sr-main", disk_full, ["--config_path=my preset.json"], capsys)
    assert pasted(line, "fix the cause and continue with: ").__getitem__(slice(0, 3)) == [
        "sr-main", "--config_path=my preset.json", "--train.resume=true"]


def test_the_viewer_hint_of_a_video_dataset_runs_as_pasted_and_writes_beside_it(spaced, tmp_path):
    from sr_imitation.recorders.viz import view_hint

    dataset = tmp_path / "video data" / "approach"
    shutil.copytree(spaced / "video data" / "approach", dataset)
    digest = dataset_digest(dataset)
    command = view_hint(dataset.name, dataset).split("view an episode: ", 1)[1].split("   (then:", 1)[0]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert [p.suffix for p in (tmp_path / "video data" / "approach_viz").iterdir()] == [".rrd"]
    assert dataset_digest(dataset) == digest  # nothing written inside the dataset
