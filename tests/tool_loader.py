"""Load a script of ``tools/`` (not a package) as a module, for the tests of the tools."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(relative: str) -> ModuleType:
    """``tools/<relative>.py`` as a module (``"test_cost"``, ``"experiments/queue_status"``)."""
    path = TOOLS / f"{relative}.py"
    spec = importlib.util.spec_from_file_location(f"tool_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
