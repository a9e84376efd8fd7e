"""The run queue's shell tools (tools/experiments): what a session leaves for the next one."""

import json
import os
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest

from tests.tool_loader import load_tool

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools" / "experiments"


def test_the_snapshot_keeps_unfinished_taken_lines_first_then_the_queue(tmp_path):
    queue = tmp_path / "queue.txt"
    queue.write_text("c -m x --seed=3\n\n# a comment\nd -m x --seed=4\n")
    (tmp_path / "queue.txt.taken").write_text("a -m x --seed=1\nb @abc1234 -m x --seed=2\ne -m x --seed=5\n")
    (tmp_path / "queue.txt.done").write_text("T start a\nT a rc=0\nT start b\nT start e\nT e rc=1\n")
    pending = tmp_path / "pending.txt"
    out = subprocess.run(["bash", str(TOOLS / "queue_snapshot.sh"), str(queue), str(pending), "f00ba47"],
                         capture_output=True, text=True, check=True).stdout
    lines = pending.read_text().splitlines()
    body = [line for line in lines if not line.startswith("#")]
    # a finished (rc=0); b running; e failed: both come back first, in the order taken, then the queue
    assert body == ["b @abc1234 -m x --seed=2", "e -m x --seed=5", "c -m x --seed=3", "d -m x --seed=4"]
    assert "the first 2 were taken" in lines[1] and "queue_worker.sh f00ba47" in lines[3]
    assert "4 line(s), 2 unfinished" in out
    assert queue.read_text().startswith("c -m x")  # the queue itself is left as it was


def _throwaway_repo(root):
    """A git repository at ``root`` with an empty tools/experiments/ (the scripts under test are copied in); returns
    ``git(*args)`` -> its stdout."""
    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True).stdout

    git("init", "-q")
    git("config", "user.email", "t@t"), git("config", "user.name", "t")
    (root / "tools" / "experiments").mkdir(parents=True)
    return git


def test_archiving_a_run_commits_it_with_the_queue_s_record_of_it(tmp_path):
    """queue_archive.sh in a throwaway clone: the run folder and queue_log.txt (header kept, the .done file's lines
    of the prefix merged, sorted, unique) in one commit of exactly those paths; a run not archived is one line."""
    git = _throwaway_repo(tmp_path)
    script = tmp_path / "tools" / "experiments" / "queue_archive.sh"
    script.write_text((TOOLS / "queue_archive.sh").read_text())
    archive = tmp_path / "docs" / "arch"
    (archive / "sr_seed1").mkdir(parents=True)
    (archive / "sr_seed1" / "results.json").write_text("{}")
    (archive / "queue_log.txt").write_text("# header\nT0 start mt5_sr_0\nT1 mt5_sr_0 rc=0\n")
    (tmp_path / "outputs").mkdir()
    (tmp_path / "outputs" / "queue.txt.done").write_text(
        "T1 mt5_sr_0 rc=0\nT2 start mt5_sr_1\nT2 start n1_sr_5\nT3 mt5_sr_1 rc=0\n")
    (tmp_path / "unrelated.txt").write_text("left alone")
    git("add", "unrelated.txt")
    out = subprocess.run(["bash", str(script), "docs/arch", "mt5_", "sr_seed1", "archive sr 1"], capture_output=True,
                         text=True, check=True).stdout
    assert "archive sr 1" in out
    assert (archive / "queue_log.txt").read_text().splitlines() == [
        "# header", "T0 start mt5_sr_0", "T1 mt5_sr_0 rc=0", "T2 start mt5_sr_1", "T3 mt5_sr_1 rc=0"]
    assert sorted(git("show", "--name-only", "--format=", "HEAD").split()) == [
        "docs/arch/queue_log.txt", "docs/arch/sr_seed1/results.json"]
    assert "unrelated.txt" in git("diff", "--cached", "--name-only")  # staged, not committed by the script
    missing = subprocess.run(["bash", str(script), "docs/arch", "mt5_", "sr_seed9", "x"], capture_output=True,
                             text=True)
    assert missing.returncode == 2
    assert missing.stderr.strip() == "queue_archive: docs/arch/sr_seed9: no such archived run"
    first = tmp_path / "docs" / "new_arch"  # the first run archived in a folder: the log starts with a header
    (first / "sr_seed100").mkdir(parents=True)
    (first / "sr_seed100" / "results.json").write_text("{}")
    subprocess.run(["bash", str(script), "docs/new_arch", "mt5_sr_1", "sr_seed100", "first"], check=True,
                   capture_output=True)
    lines = (first / "queue_log.txt").read_text().splitlines()
    assert lines[0].startswith("# Start and end") and lines[1:] == ["T2 start mt5_sr_1", "T3 mt5_sr_1 rc=0"]
    assert sorted(git("show", "--name-only", "--format=", "HEAD").split()) == [
        "docs/new_arch/queue_log.txt", "docs/new_arch/sr_seed100/results.json"]


def _resume_clone(tmp_path, pending_lines, manifest_lines, env=None):
    """A throwaway clone holding queue_resume.sh, its helpers, a pending file and a datasets manifest whose reference
    run names two skills."""
    (tmp_path / "tools" / "experiments").mkdir(parents=True)
    for name in ("queue_resume.sh", "worktree.sh", "cpu_type.sh"):
        (tmp_path / "tools" / "experiments" / name).write_text((TOOLS / name).read_text())
    header = ["# The runs still to do ...", "#   nohup setsid bash tools/experiments/queue_worker.sh abc1234 outputs/q"]
    (tmp_path / "tools" / "experiments" / "queue_pending.txt").write_text("\n".join(header + pending_lines) + "\n")
    (tmp_path / "tools" / "experiments" / "datasets.txt").write_text("\n".join(["# header", *manifest_lines]) + "\n")
    ref = tmp_path / "docs" / "ref" / "sr_seed0"
    ref.mkdir(parents=True)
    ref.joinpath("settings_fingerprint.json").write_text(
        '{"settings": {"inputs.datasets.reach-v3": "aa", "inputs.datasets.door-open-v3": "bb", "seed": 0}}')
    return subprocess.run(["bash", str(tmp_path / "tools" / "experiments" / "queue_resume.sh"), "--dry-run"],
                          capture_output=True, text=True, env=None if env is None else {**os.environ, **env})


def test_resuming_the_queue_on_a_fresh_machine_records_what_the_lines_read_and_starts_workers(tmp_path):
    """queue_resume.sh --dry-run on a clone without datasets: the folder a pending line reads is recorded by the
    manifest's recipe, every skill of the reference run's digests, from the manifest's commit; the queue file is
    written from the pending lines; workers start under the pending header's commit (one per core, 2 at most)."""
    line = "mt5_sr_3 -m x --extra=[--stream.dataset_root=datasets/mw,--wake.max_epochs=60] --seeds=[3]"
    out = _resume_clone(tmp_path, [line, "mt5_sr_4 -m x --seeds=[4]"],
                        ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld --num_episodes=100"])
    assert out.returncode == 0, out.stderr
    said = out.stderr.splitlines()
    assert said[0] == ("queue_resume: datasets/mw: recording door-open-v3 reach-v3 from c0ffee0 "
                       "(sr-record --env=metaworld --num_episodes=100)")
    assert "queue_resume: would write outputs/queue.txt: 2 line(s) from tools/experiments/queue_pending.txt" in said
    assert said.count("queue_resume: would start a worker (commit abc1234)") == min(len(os.sched_getaffinity(0)), 2)
    assert not (tmp_path / "outputs" / "queue.txt").exists() and not (tmp_path / "datasets").exists()


def test_resuming_refuses_a_dataset_without_a_recipe_and_says_when_nothing_is_left(tmp_path):
    out = _resume_clone(tmp_path, ["a -m x --extra=[--stream.dataset_root=datasets/other]"],
                        ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld"])
    assert out.returncode == 2
    assert out.stderr.strip() == ("queue_resume: datasets/other: read by a pending line, not in "
                                  "tools/experiments/datasets.txt (add its recipe)")
    done = _resume_clone(tmp_path / "empty", [], ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld"])
    assert done.returncode == 0 and done.stderr.strip().endswith("nothing left to run")


def test_resuming_while_a_worker_of_the_clone_runs_queues_nothing_twice(tmp_path):
    """A worker already running in this clone (a second call in one session): the queue file is not rewritten from
    the pending lines (one of them may be running now) and no worker is added beyond one per core."""
    fake = subprocess.Popen(["bash", "-c", "exec -a 'bash tools/experiments/queue_worker.sh abc1234 outputs/queue.txt "
                             "outputs/qlogs' sleep 60"], cwd=tmp_path)
    try:
        out = _resume_clone(tmp_path, ["mt5_sr_4 -m x --seeds=[4]"], ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld"])
    finally:
        fake.kill()
        fake.wait()
    assert out.returncode == 0, out.stderr
    assert ("queue_resume: 1 worker(s) of this clone running: outputs/queue.txt left as it is (the pending lines "
            "may be running now)") in out.stderr.splitlines()
    assert out.stderr.count("would start a worker") == min(len(os.sched_getaffinity(0)), 2) - 1


def test_the_status_names_runs_in_flight_with_their_last_position_and_what_is_queued(tmp_path):
    """queue_status.py on a queue whose run "a" ended, "b" was cut (no process of it) mid-wake and "c" is queued."""
    status = load_tool("experiments/queue_status")
    queue = tmp_path / "queue.txt"
    queue.write_text("# header\nc -m x --output_root=/nowhere/c\n")
    (tmp_path / "queue.txt.taken").write_text("a -m x --output_root=/nowhere/a\nb -m x --output_root=/nowhere/b\n")
    (tmp_path / "queue.txt.done").write_text(
        "2026-11-30T00:00:00Z start a on AMD EPYC, family 25 model 1, no AVX-512\n2026-11-30T01:00:00Z a rc=0\n"
        "2026-11-30T01:00:01Z start b on AMD EPYC, family 25 model 1, no AVX-512\n")
    logs = tmp_path / "qlogs"
    logs.mkdir()
    (logs / "b.log").write_text(
        "2026-11-30 01:00:05,000 INFO sr_imitation.stream.engine: stage 1 (reach-v3): wake\n"
        "2026-11-30 01:05:00,000 INFO sr_imitation.substrates.sac.wake: wake reach-v3: 10/300 (3%), 5m elapsed, "
        "~2h left; reward=1.0\n"
        "2026-11-30 02:00:00,000 INFO sr_imitation.stream.engine: stage 2 (door-open-v3): wake\n")
    text = status.report(queue, logs, now=datetime(2026, 11, 30, 2, 31, tzinfo=UTC))
    assert status.last_position(logs / "b.log") == ("stage 2 (door-open-v3) wake", "")
    with (logs / "b.log").open("a") as log:
        log.write("2026-11-30 02:05:00,000 INFO sr_imitation.substrates.sac.wake: wake door-open-v3: 80/800 (10%), "
                  "5m elapsed, ~45m left; reward=2.0\n")
    assert status.last_position(logs / "b.log") == (
        "stage 2 (door-open-v3) wake", "wake door-open-v3: 80/800 (10%), 5m elapsed, ~45m left; reward=2.0")
    lines = text.splitlines()
    assert lines[0] == f"queue {queue}: 1 in flight, 1 queued (0 of them requeued), 1 finished"
    assert lines[1] == ("  b: NOT running (cut: queue_requeue.sh puts it back); last started 2026-11-30T01:00:01Z "
                        "(1 h 30 min ago) on AMD EPYC, family 25 model 1, no AVX-512")
    assert lines[2] == "    stage 2 (door-open-v3) wake"  # the progress line was stage 1's
    assert lines[3:] == ["  next: c",
                         "  queued work: about 0.0 core-hours (1 of no known preset, not counted), runs in flight "
                         "not counted",
                         "  ended 2026-11-30T01:00:00Z: a rc=0"]
    # queue_requeue.sh put b back: it is queued again, no longer taken, so not in flight
    queue.write_text("# header\nb -m x --output_root=/nowhere/b\nc -m x --output_root=/nowhere/c\n")
    (tmp_path / "queue.txt.taken").write_text("a -m x --output_root=/nowhere/a\n")
    lines = status.report(queue, logs, now=datetime(2026, 11, 30, 2, 31, tzinfo=UTC)).splitlines()
    assert lines[0] == f"queue {queue}: 0 in flight, 2 queued (1 of them requeued), 1 finished"
    assert lines[1:3] == [
        "  b: requeued (resumes from its outputs when a worker takes it); last started 2026-11-30T01:00:01Z "
        "(1 h 30 min ago) on AMD EPYC, family 25 model 1, no AVX-512",
        "    stage 2 (door-open-v3) wake: wake door-open-v3: 80/800 (10%), 5m elapsed, ~45m left; reward=2.0"]
    assert lines[3] == "  next: b, c"
    # the estimate counts each queued line once, by the preset it names
    queue.write_text("# header\nd -m x --preset=configs/sac_mt5_gate.json\n"
                     "e -m x --preset=configs/needle_cpu_m16.json\n"
                     "f -m x --preset=configs/sac_mt5_gate.json --seeds=[1]\ng -m x --preset=configs/other.json\n")
    assert status.queued_hours(status._queued(queue)) == (
        "  queued work: about 4.8 core-hours (2 x configs/sac_mt5_gate.json ~2.3 h; 1 x configs/needle_cpu_m16.json "
        "~0.25 h; 1 of no known preset, not counted), runs in flight not counted")
    assert status.queued_hours(status._queued(queue), {"configs/other.json": 1.5}).startswith(
        "  queued work: about 1.5 core-hours (1 x configs/other.json ~1.5 h; 3 of no known preset")
    missing = subprocess.run(["python3", str(TOOLS / "queue_status.py"), str(tmp_path / "none.txt")],
                             capture_output=True, text=True, check=False)
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1 and "none.txt: no queue here" in missing.stderr


def test_every_queued_run_is_capped_at_avx2_unless_told_otherwise_and_its_start_line_says_so(tmp_path):
    """tools/experiments/isa_env.sh caps MKL, ATen, oneDNN, OpenBLAS and numpy at AVX2 (RESULTS' 2026-11-30 07:30
    line); SR_NATIVE_ISA=1 leaves them alone; a worker sources it and names the cap in the run's start line."""
    show = "source {}; echo \"$MKL_ENABLE_INSTRUCTIONS|$ATEN_CPU_CAPABILITY|$ONEDNN_MAX_CPU_ISA|$OPENBLAS_CORETYPE|" \
           "$NPY_DISABLE_CPU_FEATURES\"".format(TOOLS / "isa_env.sh")
    clean = {"PATH": "/usr/bin:/bin"}
    capped = subprocess.run(["bash", "-c", show], capture_output=True, text=True, env=clean).stdout.strip()
    assert capped.split("|")[:4] == ["AVX2", "avx2", "AVX2", "Haswell"]
    assert capped.split("|")[4].split() == ["AVX512F", "AVX512CD", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL",
                                            "AVX512_ICL"]
    native = subprocess.run(["bash", "-c", show], capture_output=True, text=True,
                            env={**clean, "SR_NATIVE_ISA": "1"}).stdout.strip()
    assert native == "||||"
    # A worker in a throwaway folder (no git: the line's worktree cannot be made, so it ends at once with rc=2).
    (tmp_path / "tools" / "experiments").mkdir(parents=True)
    for name in ("queue_worker.sh", "worktree.sh", "cpu_type.sh", "isa_env.sh"):
        (tmp_path / "tools" / "experiments" / name).write_text((TOOLS / name).read_text())
    queue = tmp_path / "q.txt"
    for extra, says in (({}, True), ({"SR_NATIVE_ISA": "1"}, False)):
        queue.write_text("one @abc1234 -m nothing\n")
        done = tmp_path / "q.txt.done"
        done.unlink(missing_ok=True)
        subprocess.run(["bash", str(tmp_path / "tools" / "experiments" / "queue_worker.sh"), "abc1234", str(queue),
                        str(tmp_path / "logs")], capture_output=True, text=True, check=True,
                       env={**clean, "HOME": str(tmp_path), **extra})
        start, end = done.read_text().splitlines()
        assert (", libraries capped at AVX2 (tools/experiments/isa_env.sh)" in start) is says
        assert start.split()[1:3] == ["start", "one"] and end.endswith("one rc=2")


def test_a_line_naming_other_cpu_types_waits_for_a_machine_of_its_type(tmp_path, monkeypatch):
    """A queue line "<name> @<commit> cpu=<family>/<model>,..." (tools/experiments/cpu_type.sh): a worker on another
    type takes the next line instead and leaves it queued (saying so in workers.log); a worker on a named type runs
    it, without the cpu= word among the python arguments (`-c pass` exits 0 only then); queue_resume.sh and
    queue_status.py name the waiting lines."""
    clone = tmp_path / "clone"
    (clone / "tools" / "experiments").mkdir(parents=True)
    for name in ("queue_worker.sh", "worktree.sh", "cpu_type.sh", "isa_env.sh"):
        (clone / "tools" / "experiments" / name).write_text((TOOLS / name).read_text())
    (clone / "datasets").mkdir()
    (clone / ".venv" / "bin").mkdir(parents=True)
    (clone / ".venv" / "bin" / "python").symlink_to(sys.executable)
    git = {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    for cmd in (["init", "-q"], ["add", "tools"], ["commit", "-q", "-m", "tools"]):
        subprocess.run(["git", *cmd], cwd=clone, check=True, env={**os.environ, **git})
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True, text=True,
                          check=True).stdout.strip()
    queue, logs = clone / "q.txt", clone / "logs"

    def work(cpu):
        subprocess.run(["bash", str(clone / "tools" / "experiments" / "queue_worker.sh"), head, str(queue), str(logs)],
                       check=True, env={**os.environ, "SR_CPU_TYPE": cpu, "HOME": str(tmp_path)})
        return [line.split(" ", 1)[1] for line in (clone / "q.txt.done").read_text().splitlines()]

    queue.write_text(f"w @{head} cpu=6/167,6/207 -c pass\n\none @{head} -c pass\n")
    done = work("25/1")
    assert [d.split(" on ")[0] for d in done] == ["start one", "one rc=0"]
    assert queue.read_text() == f"w @{head} cpu=6/167,6/207 -c pass\n\n"
    assert "the 1 line(s) left in" in (logs / "workers.log").read_text()
    assert "(this machine: 25/1, " in (logs / "workers.log").read_text()
    status = load_tool("experiments/queue_status")
    monkeypatch.setenv("SR_CPU_TYPE", "25/1")
    text = status.report(queue, logs)
    monkeypatch.delenv("SR_CPU_TYPE")
    assert "  waiting for another CPU type (this machine: 25/1): w (cpu=6/167,6/207)" in text.splitlines()
    assert "next:" not in text
    done = work("6/207")
    assert [d.split(" on ")[0] for d in done[2:]] == ["start w", "w rc=0"]
    assert queue.read_text().strip() == ""
    assert status.line_cpu_types(f"w @{head} cpu=6/167,6/207 -c pass") == ["6/167", "6/207"]
    assert status.line_cpu_types("w -c pass cpu=6/167") == []  # only right after the name and @commit
    assert status.line_cpu_types("w cpu=6/167 -c pass") == ["6/167"]
    # queue_resume.sh names the lines that will wait, and starts workers all the same (they take the others)
    out = _resume_clone(tmp_path / "resume", ["xgate_pw_0 @abc1234 cpu=6/167,6/207 -m x --seeds=[0]",
                                              "src_mt5_2 @abc1234 -m x --seeds=[2]"],
                        ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld"], env={"SR_CPU_TYPE": "25/1"})
    assert out.returncode == 0, out.stderr
    assert ("queue_resume: waiting for another CPU type (this machine is 25/1), not run here: xgate_pw_0"
            in out.stderr.splitlines())
    same = _resume_clone(tmp_path / "resume207", ["xgate_pw_0 @abc1234 cpu=6/167,6/207 -m x --seeds=[0]"],
                         ["mw c0ffee0 docs/ref/sr_seed0 --env=metaworld"], env={"SR_CPU_TYPE": "6/207"})
    assert same.returncode == 0 and "waiting for another CPU type" not in same.stderr


def test_protocol_w_s_pending_runs_name_the_cpu_types_their_pairs_were_made_on():
    """Protocol W's runs pair with Reset & Distill's runs made on LeRobot 0.4.4 on the Intel Xeon family 6 model 167
    (model 207 counts as its type: RESULTS' 2026-12-02 02:52 line): its five lines wait in queue_pending_v010.txt,
    which main's queue tools never read (they run from tag v0.1.0's checkout), each naming those types, so that no
    worker on another type starts it (RESULTS' 2026-12-02 07:36 line); main's own queue holds none of them."""
    w_lines = [ln for ln in (TOOLS / "queue_pending_v010.txt").read_text().splitlines()
               if "--archive=" in ln and ln.rstrip().endswith("/sac_gate_plain_wake")]
    status = load_tool("experiments/queue_status")
    assert [ln.split()[0] for ln in w_lines] == [f"xgate_pw_{s}" for s in range(5)]
    for line in w_lines:
        assert status.line_cpu_types(line) == ["6/167", "6/207"], line.split()[0]
        assert line.split()[1] == "@94cdc5a", line.split()[0]  # W's pre-registered code
    assert not [ln for ln in (TOOLS / "queue_pending.txt").read_text().splitlines() if "sac_gate_plain_wake" in ln
                and not ln.startswith("#")]


def _archived_starts(archive: Path) -> dict[str, str]:
    """``{queue line name: its last start (ISO UTC)}`` of every run an archive's ``queue_log.txt`` logs as ended."""
    _, finished = load_tool("experiments/queue_status").runs(archive / "queue_log.txt")
    return {r["name"]: r["started"] for r in finished}


def test_the_final_sleep_screening_s_runs_wait_behind_every_pre_registered_line():
    """Issue 89 item 4's protocol: its six SR runs (calibration seeds 100-102, both MT5 orders) are queued after every
    pre-registered line (each pending one waits behind every pending pre-registered line; each that ran started after
    every archived run of the replication and stream-order protocols), on the code the runs they compare with are
    pinned to, each pending one with the MT5 test preset's recorded ``--extra`` (RESULTS' 08:49 line) and, in the
    reverse order, the stream-order protocol's order; a run leaves the pending file only once archived."""
    from tests.test_results_doc import _by_id

    results = Path(__file__).resolve().parents[1] / "docs" / "results"
    lines = [ln for ln in (TOOLS / "queue_pending.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    names = [ln.split()[0] for ln in lines]
    screening = [i for i, n in enumerate(names) if n.startswith("scr_")]
    ran = {**_archived_starts(results / "order_mt5_screening_forward"),
           **_archived_starts(results / "order_mt5_screening_reverse")}
    expected = [f"scr_mt5{o}_sr_{s}" for s in (100, 101, 102) for o in "fr"]
    assert [names[i] for i in screening] == [n for n in expected if n not in ran]
    assert set(ran) <= set(expected)
    for name in ran:  # archived: its run folder is committed
        order, seed = ("reverse" if name.startswith("scr_mt5r") else "forward"), name.rsplit("_", 1)[1]
        assert (results / f"order_mt5_screening_{order}" / f"sr_seed{seed}" / "results.json").is_file(), name
    pre_registered = {n: t for a in ("lerobot06_needle_m16", "lerobot06_first_look", "lerobot06_mt5_imitation",
                                     "lerobot06_needle_vision", "lerobot06_main_job", "order_needle_m16_reverse",
                                     "order_needle_m16_forward", "order_mt5_imitation_reverse")
                      for n, t in _archived_starts(results / a).items()}
    assert len(pre_registered) >= 70 and min(ran.values(), default="9") > max(pre_registered.values())
    pending_pre_registered = [i for i, n in enumerate(names) if not n.startswith("scr_")]
    assert max(pending_pre_registered, default=-1) < min(screening, default=len(names))
    extra = _by_id("mt5-test-preset")
    skills = "button-press-topdown-v3,window-close-v3,drawer-open-v3,door-open-v3,reach-v3"
    reverse = extra[:-1] + f',"--stream.skills=[{skills}]"]'
    for i in screening:
        name, pin, *flags = lines[i].split()
        order, seed = ("reverse" if name.startswith("scr_mt5r") else "forward"), name.rsplit("_", 1)[1]
        assert pin == "@a4c8b2c" and flags == [
            "-m", "sr_imitation.experiments.needle_compare", "--preset=configs/metaworld_mt5_imitation.json",
            reverse if order == "reverse" else extra, "--variants=[sr]", f"--seeds=[{seed}]",
            f"--output_root=/work/main/outputs/order_mt5_screening_{order}/sr_{seed}",
            f"--archive=/work/main/docs/results/order_mt5_screening_{order}"], name


def test_archiving_every_finished_run_commits_each_once_and_drops_its_pending_line(tmp_path):
    """queue_archive_done.sh in a throwaway clone: of three taken lines, the one that ended rc=0 with its folder
    archived is committed (its queue lines only) and leaves the pending file; a failed run and a finished run whose
    folder is missing stay pending; a second call commits nothing."""
    git = _throwaway_repo(tmp_path)
    for name in ("queue_archive.sh", "queue_archive_done.sh"):
        (tmp_path / "tools" / "experiments" / name).write_text((TOOLS / name).read_text())
    archive = tmp_path / "docs" / "arch"
    for run in ("sr_seed1", "sr_seed2"):
        (archive / run).mkdir(parents=True)
        (archive / run / "results.json").write_text("{}")
    (archive / "queue_log.txt").write_text("# header\n")
    lines = {s: f"o_sr_{s} @abc1234 -m x --variants=[sr] --seeds=[{s}] --archive={archive}" for s in (1, 2, 3)}
    lines[11] = f"o_sr_11 @abc1234 -m x --variants=[sr] --seeds=[11] --archive={archive}"
    pending = tmp_path / "tools" / "experiments" / "queue_pending.txt"
    pending.write_text("# header\n" + "\n".join(lines.values()) + "\n")
    (tmp_path / "outputs").mkdir()
    (tmp_path / "outputs" / "queue.txt.taken").write_text("\n".join(lines[s] for s in (1, 2, 3)) + "\n")
    (tmp_path / "outputs" / "queue.txt.done").write_text(
        "T0 start o_sr_1 on AMD EPYC, family 26 model 2, AVX-512, libraries capped at AVX2 (tools/x)\n"
        "T0 start o_sr_2 on AMD EPYC\nT0 start o_sr_3 on AMD EPYC\nT0 start o_sr_11 on AMD EPYC\n"
        "T1 o_sr_1 rc=0\nT1 o_sr_2 rc=1\nT2 o_sr_3 rc=0\nT3 o_sr_11 rc=0\n")
    git("add", "tools", "outputs"), git("commit", "-q", "-m", "start")
    script = tmp_path / "tools" / "experiments" / "queue_archive_done.sh"
    first = subprocess.run(["bash", str(script)], capture_output=True, text=True, check=True)
    assert "docs/arch/sr_seed3 has no results.json" in first.stderr  # o_sr_3 finished, its folder is missing
    log = git("log", "--format=%s").splitlines()
    assert log[:2] == ["queue: archived runs leave queue_pending (o_sr_1)",
                       "archive: arch, sr seed 1 (abc1234; AMD EPYC, family 26 model 2, AVX-512, libraries capped at "
                       "AVX2)"]
    assert sorted(git("show", "--name-only", "--format=", "HEAD~1").split()) == [
        "docs/arch/queue_log.txt", "docs/arch/sr_seed1/results.json"]
    assert (archive / "queue_log.txt").read_text().splitlines() == [  # o_sr_11's lines are not o_sr_1's
        "# header", "T0 start o_sr_1 on AMD EPYC, family 26 model 2, AVX-512, libraries capped at AVX2 (tools/x)",
        "T1 o_sr_1 rc=0"]
    assert [ln.split()[0] for ln in pending.read_text().splitlines()[1:]] == ["o_sr_2", "o_sr_3", "o_sr_11"]
    again = subprocess.run(["bash", str(script)], capture_output=True, text=True, check=True)
    assert git("log", "--format=%s").splitlines() == log and "sr_seed1" not in again.stdout


def test_re_sleeping_archived_sr_runs_keeps_the_record_commits_each_once_and_skips_what_it_cannot(tmp_path):
    """resleep_archived.sh in a throwaway clone (a stand-in for sr-sleep): of four archived SR runs, the committed one
    whose outputs exist is re-slept from those outputs and its record committed without the checkpoint; an uncommitted
    one, one whose outputs are gone and one whose re-sleep fails leave nothing; a second call commits nothing; another
    candidate is handed on and kept beside the first under its own name; an unknown one is refused."""
    git = _throwaway_repo(tmp_path)
    script = tmp_path / "tools" / "experiments" / "resleep_archived.sh"
    script.write_text((TOOLS / "resleep_archived.sh").read_text())
    archive, other = tmp_path / "docs" / "arch", tmp_path / "docs" / "arch2"
    for run in ("sr_seed1", "sr_seed2", "sr_seed3", "sr_seed4", "wake_only_seed1"):
        (archive / run).mkdir(parents=True)
        (archive / run / "results.json").write_text("{}")
    lines = [f"o_sr_{s} @abc -m x --variants=[sr] --seeds=[{s}] --output_root={tmp_path}/outputs/o/sr_{s} "
             f"--archive={archive}" for s in (1, 2, 4)]
    lines.insert(0, f"p_sr_1 @abc -m x --variants=[sr] --seeds=[1] --output_root={tmp_path}/outputs/p/sr_1 "
                    f"--archive={other}")  # another archive's seed 1: not this run's outputs
    (tmp_path / "outputs").mkdir()
    (tmp_path / "outputs" / "queue.txt.taken").write_text("\n".join(lines) + "\n")
    for s in (1, 3, 4):
        (tmp_path / "outputs" / "o" / f"sr_{s}" / f"sr_seed{s}" / "memories").mkdir(parents=True)
    (tmp_path / "outputs" / "p" / "sr_1" / "sr_seed1" / "memories").mkdir(parents=True)
    git("add", "tools", "docs/arch/sr_seed1", "docs/arch/sr_seed2", "docs/arch/sr_seed4")
    git("commit", "-q", "-m", "start")
    stand_in = tmp_path / "fake_sleep.sh"
    stand_in.write_text('case "$1" in *seed4*) mkdir -p "$2"; echo half > "$2/sleep.md"; exit 1;; esac\n'
                        'mkdir -p "$2/pretrained_model"; echo "$1 $3" > "$2/sleep.json"; echo t > "$2/sleep.md"\n'
                        'echo c > "$2/checksums.json"\n')
    env = {**os.environ, "SR_RESLEEP": f"bash {stand_in}"}
    first = subprocess.run(["bash", str(script), "docs/arch/"], capture_output=True, text=True, check=True, env=env,
                           cwd=tmp_path)
    kept = archive / "sr_seed1_final_sleep_anchor_off"
    assert (kept / "sleep.json").read_text().strip() == f"{tmp_path}/outputs/o/sr_1/sr_seed1 anchor_off"
    assert sorted(p.name for p in kept.iterdir()) == ["sleep.json", "sleep.md"]
    assert git("log", "--format=%s").splitlines()[0] == (
        "archive: arch, sr seed 1's final stage re-slept with the anchor off (sr-sleep --sleep.anchor_strength=0)")
    assert sorted(git("show", "--name-only", "--format=", "HEAD").split()) == [
        "docs/arch/sr_seed1_final_sleep_anchor_off/sleep.json", "docs/arch/sr_seed1_final_sleep_anchor_off/sleep.md"]
    assert "docs/arch/sr_seed2: its outputs" in first.stderr and "are gone" in first.stderr
    assert "docs/arch/sr_seed3: not committed yet" in first.stderr
    assert "docs/arch/sr_seed4: the re-sleep failed" in first.stderr
    assert not (archive / "sr_seed4_final_sleep_anchor_off").exists()
    assert not (archive / "sr_seed2_final_sleep_anchor_off").exists()
    log = git("log", "--format=%s")
    subprocess.run(["bash", str(script), "docs/arch"], capture_output=True, text=True, check=True, env=env,
                   cwd=tmp_path)
    assert git("log", "--format=%s") == log
    subprocess.run(["bash", str(script), "--candidate=guard", "docs/arch"], capture_output=True, text=True, check=True,
                   env=env, cwd=tmp_path)
    guard = archive / "sr_seed1_final_sleep_guard"
    assert (guard / "sleep.json").read_text().strip() == f"{tmp_path}/outputs/o/sr_1/sr_seed1 guard"
    assert (kept / "sleep.json").exists()
    assert git("log", "--format=%s").splitlines()[0] == (
        "archive: arch, sr seed 1's final stage re-slept with the newest-skill guard "
        "(sr-sleep --sleep.newest_guard=true)")
    wrong = subprocess.run(["bash", str(script), "--candidate=gaurd", "docs/arch"], capture_output=True, text=True,
                           env=env, cwd=tmp_path)
    assert wrong.returncode == 2 and "--candidate=gaurd: give anchor_off, anchor_newest, guard or own" in wrong.stderr


def _resleep_args(run: Path, candidate: str, tmp_path: Path) -> list[str]:
    """resleep_final.sh's sr-sleep arguments for ``candidate`` (a stand-in sr-sleep prints them, one a line)."""
    stand_in = tmp_path / "sr-sleep"
    stand_in.write_text('#!/usr/bin/env bash\nprintf "%s\\n" "$@"\n')
    stand_in.chmod(0o755)
    out = subprocess.run(["bash", str(TOOLS / "resleep_final.sh"), str(run), str(tmp_path / "o"), candidate],
                         capture_output=True, text=True, check=True, env={**os.environ, "SR_SLEEP_BIN": str(stand_in)})
    return out.stdout.splitlines()


def test_each_screening_candidate_re_sleeps_the_run_s_final_stage_changing_only_its_own_settings(tmp_path):
    """resleep_final.sh (the final-sleep screening's C1-C3 and the run's own sleep repeated): every candidate starts
    from the newest wake with the five memories, the run's sleep settings and the final sleep's own seed; the
    candidates differ only in the anchor (off; the run's lambda toward the deployed newest wake; the run's lambda
    toward stage 4's consolidated checkpoint) and the guard; an unknown candidate is refused before sr-sleep runs."""
    run = ROOT / "docs" / "results" / "lerobot06_needle_m16" / "sr_seed2"
    cfg = json.loads((run / "train_config.json").read_text())
    skills, lam = cfg["stream"]["skills"], cfg["sleep"]["anchor_strength"]
    assert lam > 0  # the run slept with an anchor, so C1 differs from the others
    previous = f"--anchor.path={run}/skill_4_{skills[3]}/sleep/pretrained_model"
    args = {c: _resleep_args(run, c, tmp_path) for c in ("anchor_off", "anchor_newest", "guard", "own")}
    common = set.intersection(*(set(a) for a in args.values()))
    assert f"--sleep.seed={2 * 1000 + 53}" in common and f"--sleep.batch_size={cfg['sleep']['batch_size']}" in common
    assert f"--policy.path={run}/skill_5_{skills[-1]}/wake/pretrained_model" in common
    assert {c: sorted(set(a) - common) for c, a in args.items()} == {
        "anchor_off": ["--sleep.anchor_strength=0"],
        "anchor_newest": ["--final_skill=true", f"--sleep.anchor_strength={lam}"],
        "guard": [previous, "--final_skill=true", f"--sleep.anchor_strength={lam}", "--sleep.newest_guard=true"],
        "own": [previous, "--final_skill=true", f"--sleep.anchor_strength={lam}"]}
    wrong = subprocess.run(["bash", str(TOOLS / "resleep_final.sh"), str(run), str(tmp_path / "o"), "gaurd"],
                           capture_output=True, text=True, env={**os.environ, "SR_SLEEP_BIN": "false"})
    assert wrong.returncode != 0
    assert "candidate 'gaurd': give one of anchor_off, anchor_newest, guard, own" in wrong.stderr


@pytest.mark.parametrize("seed", [0, 3])
def test_the_anchor_off_re_sleep_differs_from_the_run_s_final_sleep_only_in_the_anchor(seed, tmp_path):
    """resleep_anchor_off.sh hands sr-sleep (a stand-in that prints its arguments) the run's newest wake, its five
    memories in skill order, its sleep settings with the anchor off and the final sleep's own seed (seed x 1000 + 53,
    the stream's phase seed), and the run's evaluation."""
    run = ROOT / "docs" / "results" / "lerobot06_needle_m16" / f"sr_seed{seed}"
    cfg = json.loads((run / "train_config.json").read_text())
    stand_in = tmp_path / "sr-sleep"
    stand_in.write_text('#!/usr/bin/env bash\nprintf "%s\\n" "$@"\n')
    stand_in.chmod(0o755)
    out = subprocess.run(["bash", str(TOOLS / "resleep_anchor_off.sh"), str(run), str(tmp_path / "o")],
                         capture_output=True, text=True, check=True, env={**os.environ, "SR_SLEEP_BIN": str(stand_in)})
    args = out.stdout.splitlines()
    skills = cfg["stream"]["skills"]
    assert args[0] == f"--policy.path={run}/skill_5_{skills[-1]}/wake/pretrained_model"
    assert args[1] == "--memories=[" + ",".join(f"{run}/memories/skill_{i + 1}_{s}.safetensors"
                                                 for i, s in enumerate(skills)) + "]"
    assert f"--sleep.seed={seed * 1000 + 53}" in args and "--sleep.anchor_strength=0" in args
    assert f"--sleep.lr={cfg['sleep']['lr']}" in args and f"--eval.episodes={cfg['eval']['episodes']}" in args
    assert f"--eval.skills=[{','.join(skills)}]" in args and f"--output_dir={tmp_path / 'o'}" in args
