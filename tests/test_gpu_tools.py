"""The GPU-session scripts (tools/gpu) run only on a lent GPU machine; here: they parse, and what run.sh carries
and what prepare.sh downloads agree with the pins."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools" / "gpu"
PINS = Path(__file__).resolve().parents[1] / ".ci" / "constraints.txt"


@pytest.mark.parametrize("script", ["prepare.sh", "run.sh"])
def test_the_gpu_scripts_parse(script):
    subprocess.run(["bash", "-n", str(TOOLS / script)], check=True)


def test_every_wheel_prepare_downloads_is_pinned():
    text = (TOOLS / "prepare.sh").read_text()
    names = re.search(r"for name in (.*?); do", text, re.S).group(1).replace("\\", " ").split()
    pinned = {line.split("==")[0].lower().replace("_", "-") for line in PINS.read_text().splitlines() if "==" in line}
    assert "lerobot" in names and "mujoco" in names
    assert [n for n in names if n.lower().replace("_", "-") not in pinned] == []
