"""The folder lock (:mod:`sr_imitation.infra.folder_lock`) between real processes: a second holder is refused in one
line naming the folder and the holder, a ``kill -9`` of the holder gives the lock back, every spelling of a folder has
the one lock, a process may hold it again while it holds it, and the lock file lives beside the folder (never in it)."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from sr_imitation.infra import folder_lock
from sr_imitation.infra.folder_lock import FolderBusyError, hold_folder, holds, is_lock_file, lock_path
from sr_imitation.stream.rundir import RUN_ENTRIES, run_entries_problem

HOLDER = textwrap.dedent("""
    import sys, time
    from sr_imitation.infra.folder_lock import hold_folder
    with hold_folder(sys.argv[1], "sr-holder"):
        print("held", flush=True)
        time.sleep(120)
""")


def start_holder(folder: Path) -> subprocess.Popen:
    """A process holding ``folder``'s lock until it is killed (returns once it holds it)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder), "--marker-arg"], stdout=subprocess.PIPE,
                            text=True)
    line = proc.stdout.readline()
    if line.strip() != "held":
        proc.kill()
        pytest.fail(f"the holder did not take the lock: {line!r}")
    return proc


def test_a_second_process_is_refused_in_one_line_naming_the_folder_and_the_holder(tmp_path):
    run = tmp_path / "run"
    holder = start_holder(run)
    try:
        with pytest.raises(FolderBusyError) as refused, hold_folder(run, "sr-train"):
            pytest.fail("the lock was taken twice")
        message = str(refused.value)
        assert "\n" not in message
        assert message.startswith(f"{run}: in use by sr-holder (pid {holder.pid} ")
        assert "--marker-arg" in message  # the holder's command line
        assert not run.exists()  # nothing of the folder was made by either
        assert not holds(run)
    finally:
        holder.kill()
        holder.wait()


def test_kill_9_of_the_holder_gives_the_lock_back(tmp_path):
    run = tmp_path / "run"
    holder = start_holder(run)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert lock_path(run).exists()  # the killed holder could not remove its file: the OS lock is what counts
    with hold_folder(run, "sr-train") as path:
        assert f'"pid": {os.getpid()}' in path.read_text()  # the new holder's record replaced the killed one's
    assert not path.exists()  # given back: its file removed


def test_every_spelling_of_a_folder_has_the_one_lock(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "sub")
    monkeypatch.chdir(tmp_path)
    same = {lock_path(p) for p in ("sub/run", tmp_path / "sub" / "run", "sub/../sub/run", "link/run", "./sub/run/")}
    assert same == {tmp_path / "sub" / ".run.lock"}
    assert lock_path("sub/run") != lock_path("sub/run2")


def test_a_process_holds_its_own_lock_again_and_gives_it_back_with_the_last_hold(tmp_path):
    run = tmp_path / "run"
    with hold_folder(run, "sr-main"):
        with hold_folder(run / ".." / "run", "sr-train"):  # a command whose stream locks the same folder again
            assert holds(run)
        assert holds(run) and lock_path(run).exists()
    assert not holds(run) and not lock_path(run).exists()


def test_the_lock_is_given_back_when_the_block_raises(tmp_path):
    run = tmp_path / "run"
    with pytest.raises(KeyError), hold_folder(run):
        raise KeyError("boom")
    assert not holds(run) and not lock_path(run).exists()
    holder = start_holder(run)  # another process takes it at once
    holder.kill()
    holder.wait()


def test_the_lock_file_lies_beside_the_folder_and_is_no_entry_of_a_run(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "settings_fingerprint.json").write_text("{}")
    with hold_folder(run) as path:
        assert path.parent == tmp_path and path.name == ".run.lock" and is_lock_file(path)
        assert sorted(p.name for p in run.iterdir()) == ["settings_fingerprint.json"]
        assert run_entries_problem(run) is None
    assert not any(p.name == ".run.lock" for p in run.iterdir())
    assert not is_lock_file("run") and not is_lock_file(".lock")
    assert ".run.lock" not in RUN_ENTRIES


def test_an_unwritable_parent_is_one_line_naming_it(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(OSError, match=r"run: lies in .*a_file, which is a file, not a folder") as refused, \
            hold_folder(blocker / "run"):
        pass
    assert "\n" not in str(refused.value)


CONTENDER = textwrap.dedent("""
    import os, sys, time
    from sr_imitation.infra.folder_lock import FolderBusyError, hold_folder
    folder, marker, rounds = sys.argv[1], sys.argv[2], int(sys.argv[3])
    held = 0
    deadline = time.monotonic() + 60
    while held < rounds and time.monotonic() < deadline:
        try:
            with hold_folder(folder):
                fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)  # fails if another holds it too
                time.sleep(0.001)
                os.close(fd)
                os.unlink(marker)
                held += 1
        except FolderBusyError:
            time.sleep(0.0005)
    print(held)
""")


def test_processes_taking_and_giving_back_the_lock_in_a_loop_never_hold_it_together(tmp_path):
    """The file is removed by each holder as it gives the lock back; a contender that opened the old file then locks
    a file no longer at the path, and must retry on the new one (else two would hold "the" lock at once)."""
    run, marker = tmp_path / "run", tmp_path / "inside"
    procs = [subprocess.Popen([sys.executable, "-c", CONTENDER, str(run), str(marker), "30"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(3)]
    results = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], [err[-2000:] for _, err in results]
    assert [int(out) for out, _ in results] == [30, 30, 30]
    assert not lock_path(run).exists()


def test_a_lock_taken_on_a_file_its_holder_removed_meanwhile_is_retried_on_the_current_file(tmp_path, monkeypatch):
    """Deterministically, the interleaving the loop above can only hit by chance: between this process's open and its
    flock, the holder gives the lock back (removes the file, closes it) and a third process makes and locks a new
    file. The flock on the old file then succeeds, but that file is no longer the lock: this process must retry on the
    new file and be refused, not go on as a second holder."""
    run = tmp_path / "run"
    path = lock_path(run)
    first = os.open(path, os.O_RDWR | os.O_CREAT)
    fcntl.flock(first, fcntl.LOCK_EX | fcntl.LOCK_NB)
    third: list[int] = []

    class Interleaved:
        LOCK_EX, LOCK_NB = fcntl.LOCK_EX, fcntl.LOCK_NB

        @staticmethod
        def flock(fd: int, operation: int) -> None:
            if not third:  # the holder gives the lock back; a third process locks a new file at the path
                path.unlink()
                os.close(first)
                third.append(os.open(path, os.O_RDWR | os.O_CREAT))
                fcntl.flock(third[0], fcntl.LOCK_EX | fcntl.LOCK_NB)
                os.write(third[0], b'{"pid": 424242, "command": "sr-third"}')
            fcntl.flock(fd, operation)

    monkeypatch.setattr(folder_lock, "fcntl", Interleaved)
    try:
        with pytest.raises(FolderBusyError, match=r"in use by sr-third \(pid 424242 "), hold_folder(run):
            pytest.fail("two holders at once")
    finally:
        os.close(third[0])


def test_the_refusal_waits_briefly_for_a_holder_still_writing_its_record(tmp_path, monkeypatch):
    """The record is written right after the lock is taken: a refusal in between reads it a moment later, or says
    the holder has not recorded itself yet (never a crash on an empty file)."""
    assert folder_lock.describe_holder("") == "another process (it has not recorded itself yet)"
    assert folder_lock.describe_holder("[1]") == "another process (its record is unreadable)"
    line = folder_lock.describe_holder('{"pid": 7, "host": "h", "command": "sr-eval", "since": "t", "argv": "a\\nb"}')
    assert line == "sr-eval (pid 7 on h, since t: a b)"
    started = time.monotonic()
    fd = os.open(tmp_path / "empty", os.O_RDWR | os.O_CREAT)
    try:
        assert folder_lock._read_record(fd) == ""
    finally:
        os.close(fd)
    assert time.monotonic() - started < 2


def test_folders_made_for_the_lock_are_removed_again_unless_something_was_written_there(tmp_path):
    refused = tmp_path / "a" / "b" / "run"
    with hold_folder(refused) as path:
        assert path.parent == tmp_path / "a" / "b"  # made, to hold the lock file
    assert list(tmp_path.iterdir()) == []  # a command that wrote nothing leaves no empty folders
    written = tmp_path / "c" / "d" / "run"
    with hold_folder(written):
        written.mkdir()
    assert written.is_dir() and sorted(p.name for p in written.parent.iterdir()) == ["run"]
    (tmp_path / "e").mkdir()
    with hold_folder(tmp_path / "e" / "run"):
        pass
    assert (tmp_path / "e").is_dir()  # a folder that was there before is never removed
