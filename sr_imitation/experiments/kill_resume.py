"""Kill -9 at evenly spaced moments, resume, compare: does a resumed run end exactly where an uninterrupted one does?

    python -m sr_imitation.experiments.kill_resume --moments=21 --output_root=outputs/kill_resume -- \\
        sr-train --config_path=configs/needle_cpu_m16.json --stream.skills=[approach,place] ...

The command after ``--`` is any run command that takes an output folder and a resume flag (``--output_flag``, default
``--output_dir``; ``--resume_flag``, default ``--resume=true``: ``sr-train``, ``sr-rl-train``, ``python -m
sr_imitation.substrates.act.mt_joint``; ``sr-main`` with ``--output_flag=--train.output_dir
--resume_flag=--train.resume=true``); ``{run}`` in any of its arguments becomes the run's folder (e.g.
``--record.root={run}_data``: each run records its own datasets). A console script is looked up beside this Python
first. The experiment:

1. the reference: the command with ``--output_dir=<output_root>/reference``, run to its end; its timeline: when
   ``progress.json`` recorded each phase (polled every 50 ms) and when the process ended, from its start (imports
   included);
2. for each moment i = 1..N, the reference time t_i = i T / (N + 1) (T: the reference's end), placed on its timeline as
   "after its first j phases, plus d seconds": the command with ``--output_dir=<output_root>/moment_<i>``, its whole
   process group killed with SIGKILL (nothing runs after it: no handler, no ``finally``) d seconds, scaled by this
   run's pace against the reference's, after its own j-th phase was recorded (from its start for j = 0). So the kills
   fall in the same parts of the run (recording, a wake, a sleep, an evaluation, the final writes) however the
   machine's load changes between runs; then the same command with ``--resume=true`` (or, where the kill came before
   the run wrote anything that names it a run, without it), run to its end;
3. the start-up moments (``--startup=true``, the default): the run's first writes (its settings fingerprint, then
   ``train_config.json``) take milliseconds, too short for a timed kill to hit, so each state a kill -9 can leave
   there is made from the reference's own start-up files (:func:`start_states`: the empty folder, each file's torn
   temporary copy, each file complete), then the command is run on it, resumed or plain as above;
4. each resumed run compared with the reference: every number either measured
   (:func:`~sr_imitation.reporting.compare.compare_runs`, tolerance 0), every tensor of every safetensors file
   both hold (checkpoints, memories, trajectories; bit for bit), which such files only one holds (a mid-wake
   snapshot left behind counts), and the start-up files byte for byte (:data:`START_FILES`: a resumed run without
   its ``train_config.json`` differs).

Each moment's row says what the kill interrupted (the phases recorded by then, a wake snapshot present), the resume's
exit status (with its last log line when it failed) and the verdict. Writes ``kill_resume.json`` and
``kill_resume.md`` to ``output_root`` (atomically, checked JSON) and each process's log to ``logs/``; exit 0 when every
killed run agrees, 1 otherwise. A run that ends before its kill is tried once more with half the delay, and reported
as not killed if it ends first again. The claim is "at these N moments", with the CPU named (bit-identity across CPU
types is not claimed here: one machine runs all of it).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file

from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE
from sr_imitation.io import atomic_write_bytes, write_checked_json
from sr_imitation.progress import format_duration
from sr_imitation.reporting.compare import compare_runs
from sr_imitation.stream.rundir import PROGRESS_FILE, RUN_CONFIG_FILE, RunDirectory, read_progress
from sr_imitation.stream.substrate import PHASE_IDS

logger = logging.getLogger(__name__)

POLL_S = 0.05
"""Seconds between two looks at a run's ``progress.json``."""
SNAPSHOTS = ("wake_snapshot.safetensors", "train_snapshot.safetensors")
"""Mid-wake snapshots: a run's working files, removed when their wake ends (one left behind is a difference)."""
START_FILES = (FINGERPRINT_FILE, RUN_CONFIG_FILE)
"""What a run writes at its start, in this order (:meth:`~sr_imitation.stream.rundir.RunDirectory.prepare`),
compared byte for byte."""


@dataclass
class Moment:
    """One kill and its resume."""

    index: int
    kill_at_s: float
    """Seconds from the run's start to the kill (to its end when it ended first)."""
    anchor: str = ""
    """Where the kill was placed: after the run's first j phases, plus a delay."""
    killed: bool = False
    """False when the run ended before the kill came (the machine got faster than during the reference)."""
    completed_at_kill: list[str] = field(default_factory=list)
    snapshot_at_kill: list[str] = field(default_factory=list)
    resume_rc: int | None = None
    resume_tail: str = ""
    numbers_compared: int = 0
    number_differences: list[str] = field(default_factory=list)
    tensors_compared: int = 0
    tensor_differences: list[str] = field(default_factory=list)
    file_differences: list[str] = field(default_factory=list)
    """Start-up files (:data:`START_FILES`) missing from the resumed run or not byte-identical."""

    @property
    def agrees(self) -> bool:
        return (self.resume_rc == 0 and self.numbers_compared > 0 and not self.number_differences
                and not self.tensor_differences and not self.file_differences)


def resolve(command: list[str]) -> list[str]:
    """The command with a console script of this environment (``sr-train``) found beside this Python first."""
    if not command:
        raise ValueError("give the run command after --, e.g. -- sr-train --config_path=...")
    local = Path(sys.executable).parent / command[0]
    if local.is_file():
        return [str(local), *command[1:]]
    found = shutil.which(command[0])
    if found is None:
        raise ValueError(f"command not found: {command[0]!r}")
    return [found, *command[1:]]


@dataclass(frozen=True)
class Command:
    """How to start the run command on a folder, and how to resume it."""

    args: list[str]
    output_flag: str = "--output_dir"
    resume_flag: str = "--resume=true"

    @property
    def names_its_folder(self) -> bool:
        """Whether an argument holds ``{run}`` (each run's settings then name its own folder)."""
        return any("{run}" in a for a in self.args)

    def on(self, out: Path, resume: bool) -> list[str]:
        args = [a.replace("{run}", str(out)) for a in self.args]
        return [*args, f"{self.output_flag}={out}", *([self.resume_flag] if resume else [])]


def start(command: Command, out: Path, log: Path, resume: bool) -> subprocess.Popen:
    """The run command on ``out`` in a process group of its own, its output to ``log``."""
    args = command.on(out, resume)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("ab") as sink:
        sink.write(("$ " + " ".join(args) + "\n").encode())
        sink.flush()
        return subprocess.Popen(args, stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)


def recorded_phases(run: Path) -> list[str]:
    """The phases the run's ``progress.json`` records (none before it exists; it is replaced atomically)."""
    path = run / PROGRESS_FILE
    return list(read_progress(path)["completed"]) if path.is_file() else []


@dataclass(frozen=True)
class Timeline:
    """When the reference recorded each of its phases and when it ended, in seconds from its start."""

    phases: tuple[float, ...]
    end: float

    def place(self, t: float) -> tuple[int, float, float]:
        """Reference time ``t`` as (phases recorded by then, when the last of them was (0 for none), the rest)."""
        j = sum(p <= t for p in self.phases)
        base = self.phases[j - 1] if j else 0.0
        return j, base, t - base


def run_to_end(command: Command, out: Path, log: Path, resume: bool) -> tuple[int, Timeline]:
    """Run the command to its end; its exit status and timeline."""
    t0 = time.perf_counter()
    process = start(command, out, log, resume)
    times: list[float] = []
    while process.poll() is None:
        times += [time.perf_counter() - t0] * (len(recorded_phases(out)) - len(times))
        time.sleep(POLL_S)
    end = time.perf_counter() - t0
    times += [end] * (len(recorded_phases(out)) - len(times))
    return process.returncode, Timeline(tuple(times), end)


def kill_at(command: Command, out: Path, log: Path, after_phases: int, base: float, delay: float
            ) -> tuple[bool, float]:
    """Start the command and SIGKILL its process group ``delay`` seconds (scaled by its pace: the time it took to
    record ``after_phases`` phases over the reference's ``base``) after it recorded its first ``after_phases``
    phases; whether it was killed (False: it ended first) and the seconds from its start."""
    t0 = time.perf_counter()
    process = start(command, out, log, resume=False)
    while len(recorded_phases(out)) < after_phases and process.poll() is None:
        time.sleep(POLL_S)
    reached = time.perf_counter() - t0
    pace = reached / base if after_phases and base > 0 else 1.0
    try:
        process.wait(timeout=max(0.0, pace * delay))
        return False, time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        return True, time.perf_counter() - t0


def tensor_files(run: Path) -> dict[str, Path]:
    return {str(p.relative_to(run)): p for p in sorted(run.rglob("*.safetensors")) if ".cache" not in p.parts}


def compare_tensors(reference: Path, resumed: Path) -> tuple[int, list[str]]:
    """Tensors compared, and every difference: a file only one run holds, a tensor missing or unequal."""
    a, b = tensor_files(reference), tensor_files(resumed)
    differences = [f"only in the reference: {name}" for name in sorted(a.keys() - b.keys())]
    differences += [f"only in the resumed run: {name}" for name in sorted(b.keys() - a.keys())]
    compared = 0
    for name in sorted(a.keys() & b.keys()):
        ta, tb = load_file(a[name]), load_file(b[name])
        if ta.keys() != tb.keys():
            differences.append(f"{name}: tensor names differ")
            continue
        for key in sorted(ta):
            compared += 1
            if ta[key].shape != tb[key].shape or ta[key].dtype != tb[key].dtype or not torch.equal(ta[key], tb[key]):
                differences.append(f"{name}: {key}")
    return compared, differences


def compare_start_files(reference: Path, resumed: Path, names_its_folder: bool = False) -> list[str]:
    """The start-up files (:data:`START_FILES`) the resumed run lacks or holds with other bytes than the reference.
    ``names_its_folder`` (a ``{run}`` in the command, e.g. ``--record.root={run}_data``): each run's settings then
    hold its own folder, so the files are compared as JSON with each run's folder written ``{run}`` and the seal
    (a sha256 over those bytes) set aside; otherwise byte for byte."""
    differences = []
    for name in START_FILES:
        a, b = reference / name, resumed / name
        if a.is_file() != b.is_file():
            differences.append(f"only in the {'reference' if a.is_file() else 'resumed run'}: {name}")
        elif a.is_file() and (_unplaced(a, reference) != _unplaced(b, resumed) if names_its_folder
                              else a.read_bytes() != b.read_bytes()):
            differences.append(f"{name}: bytes differ")
    return differences


def _unplaced(path: Path, run: Path) -> Any:
    """A start-up file's JSON with its run's folder written ``{run}`` and without its seal."""
    data = json.loads(path.read_text().replace(str(run), "{run}"))
    if isinstance(data, dict):
        data.pop("sha256", None)
    return data


def start_states(reference: Path) -> list[tuple[str, dict[str, bytes]]]:
    """What a kill -9 during the run's start-up writes leaves, made from the reference's own start-up files: the
    empty folder (killed before the first write), then for each of :data:`START_FILES` in order its atomic write's
    torn temporary file (killed inside the write) and the file itself (killed after it). Each as (where the kill
    came, {name: bytes})."""
    states: list[tuple[str, dict[str, bytes]]] = [("after the folder was made", {})]
    files: dict[str, bytes] = {}
    for name in START_FILES:
        data = (reference / name).read_bytes()
        states.append((f"inside the write of {name}", {**files, f".{name}.killed.tmp": data[:len(data) // 2]}))
        files[name] = data
        states.append((f"after {name}", dict(files)))
    return states


def last_line(log: Path) -> str:
    lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1][:300] if lines else ""


def snapshots_in(run: Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for name in SNAPSHOTS for p in run.rglob(name))


def in_order(completed: list[str]) -> list[str]:
    """Recorded phases (``"<stage>.<phase>"``, stored sorted by name) in the order a run completes them."""
    def key(name: str) -> tuple[int, int, str]:
        stage, _, phase = name.partition(".")
        return (int(stage) if stage.isdigit() else 0, PHASE_IDS.get(phase, len(PHASE_IDS)), phase)
    return sorted(completed, key=key)


def run_moment(command: Command, root: Path, reference: Path, index: int, place: tuple[int, float, float],
               name: str) -> Moment:
    out, log = root / name, root / "logs" / f"{name}.log"
    after, base, delay = place
    moment = Moment(index, 0.0, f"after {after} phase(s) + {delay:.1f} s")
    moment.killed, seconds = kill_at(command, out, log, after, base, delay)
    moment.kill_at_s = round(seconds, 2)
    if not moment.killed:  # it ended first; that run is done
        return moment
    if out.is_dir():
        moment.completed_at_kill = in_order(recorded_phases(out))
        moment.snapshot_at_kill = snapshots_in(out)
    return finish_moment(command, out, log, reference, moment)


def run_start_moment(command: Command, root: Path, reference: Path, index: int, state: tuple[str, dict[str, bytes]],
                     name: str) -> Moment:
    """A start-up moment: the folder as a kill during the start-up writes leaves it (:func:`start_states`), then
    the command run on it and compared as after a timed kill."""
    out, log = root / name, root / "logs" / f"{name}.log"
    where, files = state
    out.mkdir(parents=True)
    for file, data in files.items():
        (out / file).write_bytes(data)
    return finish_moment(command, out, log, reference, Moment(index, 0.0, f"start-up: {where}", killed=True))


def finish_moment(command: Command, out: Path, log: Path, reference: Path, moment: Moment) -> Moment:
    """Run the command on the killed run to its end and compare the result with the reference."""
    # a kill before the run wrote its settings leaves nothing to resume: the command starts it again
    resumable = RunDirectory.occupied(out)
    moment.resume_rc, _ = run_to_end(command, out, log, resume=resumable)
    if moment.resume_rc != 0:
        moment.resume_tail = last_line(log)
        return moment
    moment.file_differences = compare_start_files(reference, out, command.names_its_folder)
    report = compare_runs(reference, out, 0.0)
    moment.numbers_compared = report["compared"]
    moment.number_differences = [f"{p}: {a!r} != {b!r}" for p, a, b, _ in report["differences"]]
    moment.number_differences += [f"only in the reference: {p}" for p in report["only_a"]]
    moment.number_differences += [f"only in the resumed run: {p}" for p in report["only_b"]]
    moment.tensors_compared, moment.tensor_differences = compare_tensors(reference, out)
    return moment


def render(command: Command, reference_s: float, moments: list[Moment], cpu: str) -> str:
    killed = [m for m in moments if m.killed]
    agree = sum(m.agrees for m in killed)
    late = len(moments) - len(killed)
    lines = [f"# Kill -9 and resume at {len(moments)} moments", "",
             f"Command: `{' '.join(command.on(Path('<run>'), resume=False))}` (resumed with `{command.resume_flag}`); "
             f"machine: {cpu}; reference run {format_duration(reference_s)}.", "",
             f"**{agree} of {len(killed)} killed runs agree** with the uninterrupted run after their resume (every "
             "measured number and every checkpoint, memory and trajectory tensor, bit for bit)"
             + (f"; {late} moment(s) came after the run had ended (tried twice, the second time with half the delay)"
                if late else "") + ".", "",
             "| moment | placed | kill at (s) | phases recorded at the kill | wake snapshot | resume | numbers | "
             "tensors | verdict |", "|---|---|---|---|---|---|---|---|---|"]
    for m in moments:
        done = (m.completed_at_kill[-1] + f" ({len(m.completed_at_kill)})") if m.completed_at_kill else "none"
        if not m.killed:
            done = f"ended first ({m.kill_at_s:.1f} s)"
        verdict = "not killed" if not m.killed else "agrees" if m.agrees else "DIFFERS"
        resume = "-" if not m.killed else "ok" if m.resume_rc == 0 else f"exit {m.resume_rc}: {m.resume_tail}"
        snapshot = ", ".join(m.snapshot_at_kill) or "-"
        lines.append(f"| {m.index} | {m.anchor} | {m.kill_at_s} | {done} | {snapshot} | {resume} | "
                     f"{m.numbers_compared} ({len(m.number_differences)} differ) | {m.tensors_compared} "
                     f"({len(m.tensor_differences)} differ) | {verdict} |")
    for m in moments:
        differences = m.file_differences + m.number_differences + m.tensor_differences
        if not m.agrees and differences:
            lines += ["", f"Moment {m.index}: " + "; ".join(differences[:10])]
    return "\n".join(lines) + "\n"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f", {os.cpu_count()} cores"
    except OSError:
        pass
    return "unknown CPU"


def main(args: list[str] | None = None) -> int:
    setup_logging()
    args = sys.argv[1:] if args is None else args
    split = args.index("--") if "--" in args else len(args)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moments", type=int, default=21, help="kills, evenly spaced over the reference's time")
    parser.add_argument("--output_root", type=Path, required=True, help="a new folder for every run and the report")
    parser.add_argument("--output_flag", default="--output_dir", help="the command's flag naming its run folder")
    parser.add_argument("--resume_flag", default="--resume=true", help="the command's flag that resumes a run")
    parser.add_argument("--startup", type=lambda v: v.lower() in ("1", "true", "yes"), default=True,
                        help="also the states a kill during the start-up writes leaves (true/false)")
    ns = parser.parse_args(args[:split])
    if ns.moments < 1:
        raise ValueError(f"--moments must be >= 1, got {ns.moments}")
    command = Command(resolve(args[split + 1:]), ns.output_flag, ns.resume_flag)
    root: Path = ns.output_root
    if root.exists() and any(root.iterdir()):
        raise FileExistsError(f"{root} is not empty; choose a new --output_root")
    reference = root / "reference"
    logger.info("reference run: %s", " ".join(command.on(reference, resume=False)))
    rc, timeline = run_to_end(command, reference, root / "logs" / "reference.log", resume=False)
    if rc != 0:
        raise RuntimeError(f"the reference run failed (exit {rc}): {last_line(root / 'logs' / 'reference.log')}")
    reference_s = timeline.end
    logger.info("reference run: %s, %d phases; now %d kills", format_duration(reference_s), len(timeline.phases),
                ns.moments)
    moments = []
    for i in range(1, ns.moments + 1):
        after, base, delay = timeline.place(reference_s * i / (ns.moments + 1))
        for name, d in ((f"moment_{i:02d}", delay), (f"moment_{i:02d}_again", delay / 2)):
            moment = run_moment(command, root, reference, i, (after, base, d), name)
            if moment.killed:
                break
        moments.append(moment)
        logger.info("moment %d/%d (%s: at %.1f s, after %s): %s", i, ns.moments, moment.anchor, moment.kill_at_s,
                    moment.completed_at_kill[-1] if moment.completed_at_kill else "no phase",
                    "not killed" if not moment.killed else "agrees" if moment.agrees else "DIFFERS")
    if ns.startup and command.names_its_folder:
        logger.info("no start-up moments: they are made from the reference's own files, which name its folder "
                    "through {run}; give the command its inputs by a fixed path to test them")
    for j, state in enumerate(start_states(reference) if ns.startup and not command.names_its_folder else [], 1):
        moment = run_start_moment(command, root, reference, ns.moments + j, state, f"start_{j:02d}")
        moments.append(moment)
        logger.info("moment %d (%s): %s", moment.index, moment.anchor, "agrees" if moment.agrees else "DIFFERS")
    cpu = cpu_name()
    write_checked_json(root / "kill_resume.json", {
        "command": asdict(command), "cpu": cpu, "reference_seconds": reference_s,
        "reference_phases_at": list(timeline.phases),
        "moments": [asdict(m) | {"agrees": m.agrees} for m in moments]})
    atomic_write_bytes(root / "kill_resume.md", render(command, reference_s, moments, cpu).encode())
    killed = [m for m in moments if m.killed]
    agree = sum(m.agrees for m in killed)
    logger.info("%d of %d killed runs agree: %s", agree, len(killed), root / "kill_resume.md")
    return 0 if killed and agree == len(killed) else 1


def entry() -> None:
    sys.exit(run_cli("sr_imitation.experiments.kill_resume", main))


if __name__ == "__main__":
    entry()
