"""Packaging: the plugin distribution is discoverable by LeRobot, the core stays substrate-free."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_plugin_distribution_name_equals_its_import_name():
    dist = importlib.metadata.distribution("lerobot_policy_act_sr")
    assert dist.metadata["Name"] == "lerobot_policy_act_sr"


def test_lerobot_discovers_and_imports_the_plugin():
    code = (
        "import sys\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "assert 'lerobot_policy_act_sr' in sys.modules, sorted(m for m in sys.modules if 'policy' in m)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=300)


def test_core_imports_neither_lerobot_nor_simulators():
    code = (
        "import sys, sr_imitation.core\n"
        "bad = [m for m in ('lerobot', 'metaworld', 'mujoco', 'gymnasium') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=120)


def test_no_top_level_package_shadows_hugging_face_datasets():
    for name in ("datasets", "policies"):
        assert not (ROOT / name / "__init__.py").exists(), f"{name}/ must not be an importable package"
    import datasets  # Hugging Face datasets, which LeRobot imports

    assert Path(datasets.__file__).resolve().parent.parent.name == "site-packages"
