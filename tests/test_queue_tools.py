"""The run queue's shell tools (tools/experiments): what a session leaves for the next one."""

import subprocess
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools" / "experiments"


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
