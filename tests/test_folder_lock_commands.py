"""Every command that writes a run or output folder takes the folder's lock (:mod:`sr_imitation.infra.folder_lock`)
before it looks at the folder: while another process holds it, ``sr-train`` (both substrates), ``sr-main``,
``sr-eval``, ``sr-sleep``, ``sr-record`` (its dataset root, both recorders) and ``sr-grid`` (each run) are refused in
one line naming the folder and the holder, and the folder is left as it was. (Two real writers of one run are
tests/stream/test_two_writers.py; the lock itself tests/infra/test_folder_lock.py.)"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.folder_lock import FolderBusyError

REPO = Path(__file__).resolve().parents[1]
HOLDER = textwrap.dedent("""
    import sys, time
    from sr_imitation.infra.folder_lock import hold_folder
    with hold_folder(sys.argv[1], "sr-other"):
        print("held", flush=True)
        time.sleep(300)
""")


@pytest.fixture
def held(tmp_path) -> Iterator[Callable[[Path], int]]:
    """``held(folder)``: another process holds ``folder``'s lock until the test ends; returns its pid."""
    procs: list[subprocess.Popen] = []

    def hold(folder: Path) -> int:
        proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert proc.stdout.readline().strip() == "held"
        return proc.pid

    yield hold
    for proc in procs:
        proc.kill()
        proc.wait()


def refused(folder: Path, pid: int, call: Callable[[], object]) -> None:
    """``call()`` is refused because ``folder`` is held by ``pid``, and leaves ``folder`` as it was."""
    before = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else None
    with pytest.raises(FolderBusyError) as exc:
        call()
    assert str(exc.value).startswith(f"{folder}: in use by sr-other (pid {pid} ")
    assert (sorted(p.name for p in folder.iterdir()) if folder.is_dir() else None) == before


def test_sr_train_on_either_substrate_and_sr_main(tmp_path, held):
    from sr_imitation import cli, main_job

    out = tmp_path / "run"
    pid = held(out)
    preset = str(REPO / "configs" / "needle_cpu.json")
    refused(out, pid, lambda: cli.train_main([f"--config_path={preset}", f"--output_dir={out}"]))
    refused(out, pid, lambda: cli.train_main(["--substrate=sac", f"--output_dir={out}"]))
    refused(out, pid, lambda: main_job.main([f"--config_path={preset}", f"--train.output_dir={out}",
                                             f"--record.root={tmp_path / 'datasets'}"]))
    assert not (tmp_path / "datasets").exists()  # refused before recording anything


def test_sr_eval_and_sr_sleep_lock_their_output_dir(tmp_path, held):
    from sr_imitation.substrates.act import cli

    out = tmp_path / "eval"
    out.mkdir()
    (out / "eval.json").write_text("{}")  # an earlier evaluation: looked at only by the lock's holder
    pid = held(out)
    refused(out, pid, lambda: cli.eval_main([f"--policy.path={tmp_path / 'no_model'}", f"--output_dir={out}"]))
    slept = tmp_path / "slept"
    pid = held(slept)
    refused(slept, pid, lambda: cli.sleep_main([f"--policy.path={tmp_path / 'no_model'}", f"--output_dir={slept}",
                                                f"--memories=[{tmp_path / 'a.safetensors'}]"]))


def test_sr_record_locks_the_dataset_root(tmp_path, held, capsys):
    from sr_imitation.recorders import cli

    root = tmp_path / "datasets"
    pid = held(root)
    refused(root, pid, lambda: cli.main([f"--root={root}", "--skills=[approach]", "--num_episodes=1"]))
    refused(root, pid, lambda: cli.main(["--env=metaworld", f"--root={root}", "--skills=[reach-v3]",
                                         "--num_episodes=1"]))
    with pytest.raises(SystemExit) as exc:  # through the console script: one line, exit status 2
        run_cli("sr-record", cli.main, [f"--root={root}", "--skills=[approach]", "--num_episodes=1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"sr-record: error: {root}: in use by sr-other (pid {pid} ")


def test_sr_grid_locks_each_run_before_deciding_to_resume_it(tmp_path, held):
    from sr_imitation.experiments.grid import run_one

    out = tmp_path / "sr_seed0"
    pid = held(out)
    ran = []
    substrate = SimpleNamespace(run=lambda variant, run: ran.append(variant))
    refused(out, pid, lambda: run_one(substrate, "sr", SimpleNamespace(output_dir=out, resume=False)))
    assert ran == []
    info = run_one(substrate, "sr", SimpleNamespace(output_dir=tmp_path / "sr_seed1", resume=False))
    assert ran == ["sr"] and info["resumed_phases"] == []
