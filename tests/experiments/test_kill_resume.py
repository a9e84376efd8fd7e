"""The kill -9 experiment (sr_imitation.experiments.kill_resume): real SIGKILLs of a real ``sr-train`` process (the
toy substrate, so that it takes seconds), resumed and compared with the uninterrupted run; and the comparison finds a
changed tensor and a file only one run holds."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from sr_imitation.experiments import kill_resume
from sr_imitation.io import read_checked_json

# sr-train with the toy substrate registered (what the recipe's substrate folder registers), as a process of its own
TOY_TRAIN = ["python", "-c", "from sr_imitation import cli; from sr_imitation.substrates import registry as r; "
             "r.register_substrate(type('Toy', (r.SubstrateCommand,), {'name': 'toy', 'module': 'tests.stream.toy'}));"
             " cli.train_entry()",
             "--substrate=toy", "--stream.skills=[a,b,c]", "--progress=false", "--wake_steps=1000"]


@pytest.mark.slow
def test_runs_killed_with_sigkill_and_resumed_agree_with_the_uninterrupted_one(tmp_path):
    root = tmp_path / "kill"
    # (the start-up moments: test_the_start_up_moments_are_run_again_and_compared_file_by_file)
    assert kill_resume.main(["--moments=2", "--startup=false", f"--output_root={root}", "--", *TOY_TRAIN]) == 0
    report = read_checked_json(root / "kill_resume.json")
    moments = report["moments"]
    killed = [m for m in moments if m["killed"]]
    assert len(moments) == 2 and killed  # at least one kill came while the run was running
    # placed on the reference's phase timeline: the later kill waited for the phases the reference had by then
    after = sum(p <= report["reference_seconds"] * 2 / 3 for p in report["reference_phases_at"])
    assert after > 0 and moments[1]["anchor"].startswith(f"after {after} phase(s)")
    assert not moments[1]["killed"] or len(moments[1]["completed_at_kill"]) >= after
    assert all(m["agrees"] and m["resume_rc"] == 0 for m in killed)
    assert all(m["numbers_compared"] > 0 and m["tensors_compared"] > 0 for m in killed)
    md = (root / "kill_resume.md").read_text()
    assert f"**{len(killed)} of {len(killed)} killed runs agree**" in md and report["cpu"] in md
    with pytest.raises(FileExistsError, match="not empty"):  # nothing already written is touched
        kill_resume.main(["--moments=1", f"--output_root={root}", "--", *TOY_TRAIN])


def test_the_tensor_comparison_names_a_changed_tensor_and_a_file_only_one_run_holds(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for run, value in ((a, 1.0), (b, 2.0)):
        (run / "stage").mkdir(parents=True)
        save_file({"w": torch.tensor([value]), "same": torch.zeros(2)}, run / "stage" / "model.safetensors")
    save_file({"x": torch.zeros(1)}, b / "stage" / "wake_snapshot.safetensors")  # a snapshot left behind
    compared, differences = kill_resume.compare_tensors(a, b)
    assert compared == 2
    assert differences == ["only in the resumed run: stage/wake_snapshot.safetensors", "stage/model.safetensors: w"]


def test_the_command_is_required_and_must_exist(tmp_path):
    with pytest.raises(ValueError, match="give the run command after --"):
        kill_resume.main([f"--output_root={tmp_path / 'k'}"])
    with pytest.raises(ValueError, match="command not found: 'no-such-command'"):
        kill_resume.main([f"--output_root={tmp_path / 'k'}", "--", "no-such-command"])


def test_the_command_names_its_folder_where_it_asks_and_resumes_with_its_own_flag(tmp_path):
    command = kill_resume.Command(["sr-main", "--record.root={run}_data"], "--train.output_dir",
                                  "--train.resume=true")
    assert command.on(tmp_path / "m1", resume=False) == [
        "sr-main", f"--record.root={tmp_path}/m1_data", f"--train.output_dir={tmp_path}/m1"]
    assert command.on(tmp_path / "m1", resume=True)[-1] == "--train.resume=true"


def test_a_reference_time_is_placed_after_the_phases_recorded_by_then():
    timeline = kill_resume.Timeline((2.0, 5.0, 5.0, 9.0), 12.0)  # two phases recorded in the same poll at 5 s
    assert timeline.place(1.0) == (0, 0.0, 1.0)  # before the first phase: from the start
    assert timeline.place(6.0) == (3, 5.0, 1.0)
    assert timeline.place(11.0) == (4, 9.0, 2.0)  # after the last phase: the final writes


def test_the_start_up_moments_are_run_again_and_compared_file_by_file(tmp_path, monkeypatch):
    """Each state a kill during the start-up writes leaves (:func:`kill_resume.start_states`) is run again (resumed
    where the folder holds a run) and compared with the reference, ``train_config.json`` byte for byte; the command
    runs in this process here (the toy's ``sr-train`` entry) to keep it to seconds. Before: the moments after the
    fingerprint resumed without a ``train_config.json``."""
    from tests.stream import toy

    command = kill_resume.Command(["--stream.skills=[a,b]", "--progress=false", "--wake_steps=10"])
    calls = []

    def in_process(command, out, log, resume):
        calls.append(resume)
        toy.main(command.on(out, resume))
        return 0, kill_resume.Timeline((), 0.0)

    monkeypatch.setattr(kill_resume, "run_to_end", in_process)
    reference = tmp_path / "reference"
    in_process(command, reference, None, False)
    moments = [kill_resume.run_start_moment(command, tmp_path, reference, 10 + j, state, f"start_{j:02d}")
               for j, state in enumerate(kill_resume.start_states(reference), 1)]
    assert calls == [False, False, False, True, True, True]  # reference, then plain, plain, resume x3
    assert [m.file_differences for m in moments] == [[]] * 5
    assert all(m.agrees and m.numbers_compared > 0 for m in moments)
    md = kill_resume.render(command, 1.0, moments, "cpu")
    assert "**5 of 5 killed runs agree**" in md and "start-up: inside the write of train_config.json" in md
    # a resumed run without the file is a difference, named in the report
    (tmp_path / "start_05" / "train_config.json").unlink()
    assert kill_resume.compare_start_files(reference, tmp_path / "start_05") == [
        "only in the reference: train_config.json"]


def test_start_files_of_commands_that_name_their_folder_compare_with_the_folder_set_aside(tmp_path):
    """``--record.root={run}_data`` puts each run's own folder into its settings (and into the seal over them): the
    start-up files then compare as JSON with the folder written {run} and the seal set aside (before: every such
    run differed, 2026-11-29); a real difference still shows, and without {run} the bytes decide."""
    from sr_imitation.io import write_checked_json

    def run(name: str, lr: float) -> Path:
        out = tmp_path / name
        out.mkdir()
        for file in kill_resume.START_FILES:
            write_checked_json(out / file, {"record": {"root": f"{out}_data"}, "lr": lr})
        return out

    reference, same, other = run("reference", 0.1), run("moment_01", 0.1), run("moment_02", 0.2)
    assert kill_resume.Command(["sr-main", "--record.root={run}_data"]).names_its_folder
    assert not kill_resume.Command(["sr-train", "--seed=1"]).names_its_folder
    assert kill_resume.compare_start_files(reference, same, names_its_folder=True) == []
    assert kill_resume.compare_start_files(reference, other, names_its_folder=True) == [
        f"{name}: bytes differ" for name in kill_resume.START_FILES]
    assert kill_resume.compare_start_files(reference, same) == [
        f"{name}: bytes differ" for name in kill_resume.START_FILES]
