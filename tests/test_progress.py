"""Progress on long work (sr_imitation.progress) and the commands' logging set-up: a run whose standard error is a
file gets readable log lines (counts, elapsed, time left), never carriage-return redraws; INFO lines survive
LeRobot's import."""

from __future__ import annotations

import logging
import subprocess
import sys

import torch
from torch import nn

from sr_imitation import progress as progress_module
from sr_imitation.core.memory import OutputDistillationMemory
from sr_imitation.core.sleep import SleepConfig, sleep_consolidate
from sr_imitation.progress import Progress, interactive

LOGGER = logging.getLogger("sr_imitation.test_progress")


def test_forced_forms(monkeypatch):
    monkeypatch.setenv("SR_PROGRESS", "bar")
    assert interactive()
    monkeypatch.setenv("SR_PROGRESS", "log")
    assert not interactive()


def test_off_a_terminal_it_logs_count_elapsed_time_left_and_the_latest_values(monkeypatch, caplog):
    monkeypatch.setenv("SR_PROGRESS", "log")
    caplog.set_level(logging.INFO, logger=LOGGER.name)
    with Progress(10, "wake approach", LOGGER, every_s=0.0) as bar:
        assert bar.bar is None
        bar.update(1)
        bar.set_postfix(val_l1="0.4512")
        bar.update(2)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert lines[0].startswith("wake approach: 1/10 (10%), ") and "elapsed" in lines[0] and "left" in lines[0]
    assert lines[1].startswith("wake approach: 3/10 (30%), ") and lines[1].endswith("; val_l1=0.4512")


def test_a_resumed_loop_counts_what_was_done_and_estimates_from_what_this_bar_saw(monkeypatch, caplog):
    monkeypatch.setenv("SR_PROGRESS", "log")
    caplog.set_level(logging.INFO, logger=LOGGER.name)
    clock = iter([0.0, 10.0, 10.0])  # start; one step 10 s later; the line's time
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: next(clock))
    bar = Progress(100, "wake reach", LOGGER, every_s=0.0, initial=50)
    bar.update(1)  # 51 of 100 done; this bar saw one step in 10 s: 49 left, ~490 s
    line, = [r.getMessage() for r in caplog.records]
    assert line.startswith("wake reach: 51/100 (51%), 10s elapsed, ~8m10s left"), line


def test_lines_are_throttled_and_disabled_progress_says_nothing(monkeypatch, caplog):
    monkeypatch.setenv("SR_PROGRESS", "log")
    caplog.set_level(logging.INFO, logger=LOGGER.name)
    bar = Progress(100, "sleep k=2", LOGGER, every_s=3600.0)
    for _ in range(100):
        bar.update()
    assert caplog.records == []  # an hour has not passed
    bar.log()
    assert [r.getMessage().split(",")[0] for r in caplog.records] == ["sleep k=2: 100/100 (100%)"]
    assert "left" not in caplog.records[0].getMessage()  # done: no estimate
    silent = Progress(5, "eval", LOGGER, enabled=False, every_s=0.0)
    for _ in range(5):
        silent.update()
    assert silent.bar is None and len(caplog.records) == 1


def test_on_a_terminal_it_is_a_bar_and_logs_nothing(monkeypatch, caplog):
    monkeypatch.setenv("SR_PROGRESS", "bar")
    caplog.set_level(logging.INFO, logger=LOGGER.name)
    with Progress(3, "record approach", LOGGER, every_s=0.0, unit="ep") as bar:
        for _ in range(3):
            bar.update()
        assert bar.bar is not None and bar.n == 3
    assert caplog.records == []


def test_a_sleep_off_a_terminal_writes_log_lines_and_no_redraws(monkeypatch, caplog, capsys):
    monkeypatch.delenv("SR_PROGRESS", raising=False)  # pytest's captured stderr is not a terminal
    monkeypatch.setattr(progress_module, "EVERY_S", 0.0)
    caplog.set_level(logging.INFO, logger="sr_imitation.core.sleep")
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(2, 8), nn.Tanh(), nn.Linear(8, 2))
    memories = [OutputDistillationMemory.from_snapshot(name, lambda obs: net(obs["x"]), {"x": torch.randn(32, 2)})
                for name in ("a", "b")]
    config = SleepConfig(lr=1e-3, max_iterations=12, batch_size=8, anchor_tau=None, early_stop_window=50, seed=0)
    sleep_consolidate(list(net.parameters()), lambda obs: net(obs["x"]), memories, config, progress=True)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("sleep k=2: ")]
    assert len(lines) == 12 and lines[-1].startswith("sleep k=2: 12/12 (100%)")
    assert "obj=" in lines[-1] and "worst=" in lines[-1]
    assert "\r" not in capsys.readouterr().err


def test_commands_log_info_lines_after_lerobot_is_imported():
    """LeRobot's import runs logging.basicConfig() at WARNING (a module-level logging.debug); the commands' set-up
    must still give INFO lines in our format (before the fix a two-hour run logged nothing)."""
    code = ("import lerobot.utils.import_utils, logging\n"
            "from sr_imitation.infra.cli_errors import setup_logging\n"
            "assert logging.getLogger().handlers, 'LeRobot no longer installs a handler: the test is moot'\n"
            "setup_logging()\n"
            "logging.getLogger('sr_imitation.check').info('an info line')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith(" INFO sr_imitation.check: an info line"), done.stderr


def test_durations_read_as_the_progress_lines_write_them():
    from sr_imitation.progress import format_duration

    assert [format_duration(s) for s in (0, 42.4, 187, 3900, 90061)] == ["0s", "42s", "3m07s", "1h05m", "25h01m"]


def test_a_grid_says_how_long_its_other_runs_will_take_at_the_pace_so_far(tmp_path):
    from sr_imitation.experiments.grid import _finished_line

    info = {"resumed_phases": ["1.wake"], "wall_s": 300.0, "run_dir": tmp_path}  # no results.json: AFSR -
    line = _finished_line(("sr", 3), info, 2, 5, elapsed=600.0)
    assert line == ("finished sr seed 3: AFSR -, 300.0 s, resumed with 1 phase done "
                    "(2/5; the other 3 at this pace: ~15m00s)")
    assert _finished_line(("sr", 3), info, 5, 5, elapsed=600.0).endswith("(5/5)")
