"""Packaging: the plugin distribution is discoverable by LeRobot, the core stays substrate-free."""

from __future__ import annotations

import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["lerobot_policy_act_sr", "lerobot_env_sr"])
def test_plugin_distribution_name_equals_its_import_name(name):
    dist = importlib.metadata.distribution(name)
    assert dist.metadata["Name"] == name


def _run_json(code: str, timeout: int) -> dict:
    """Run ``code`` in a fresh interpreter (imports must start clean) and parse the JSON it prints last."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_lerobot_discovers_and_imports_the_plugin():
    found = _run_json(
        "import json, sys\n"
        "before = 'lerobot_policy_act_sr' in sys.modules\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "print(json.dumps({'before': before, 'after': 'lerobot_policy_act_sr' in sys.modules,\n"
        "                  'choices': sorted(PreTrainedConfig.get_known_choices())}))\n",
        timeout=300,
    )
    # Imported by LeRobot's discovery (not before it), and the policy type is registered with draccus.
    assert found["before"] is False and found["after"] is True
    assert "act_sr" in found["choices"] and "act" in found["choices"]


def test_lerobot_discovers_the_env_plugin_and_the_policy_plugin_registers_no_env():
    """The environments are registered by the env plugin (LeRobot 0.6's ``lerobot_env_*`` discovery), not as a side
    effect of importing the policy plugin."""
    found = _run_json(
        "import json, sys\n"
        "import lerobot_policy_act_sr\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "by_policy = sorted({'needle', 'sr_meta_world'} & set(EnvConfig.get_known_choices()))\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "print(json.dumps({'by_policy': by_policy, 'env_plugin': 'lerobot_env_sr' in sys.modules,\n"
        "                  'choices': sorted({'needle', 'sr_meta_world'} & set(EnvConfig.get_known_choices()))}))\n",
        timeout=300,
    )
    assert found["by_policy"] == [] and found["env_plugin"] is True
    assert found["choices"] == ["needle", "sr_meta_world"]


def test_core_and_stream_engine_import_neither_lerobot_nor_simulators():
    """The layers below the substrates (io, core, infra, stream) import neither LeRobot nor a simulator."""
    found = _run_json(
        "import json, sys\n"
        "import sr_imitation.io\n"
        "import sr_imitation.core, sr_imitation.core.sleep, sr_imitation.core.memory, sr_imitation.core.metrics\n"
        "import sr_imitation.core.aggregation, sr_imitation.core.excitability\n"
        "import sr_imitation.infra, sr_imitation.infra.fingerprint, sr_imitation.infra.runlog\n"
        "import sr_imitation.infra.provenance, sr_imitation.infra.cli_errors, sr_imitation.infra.cli_parsing\n"
        "import sr_imitation.stream, sr_imitation.stream.engine, sr_imitation.stream.methods\n"
        "print(json.dumps({'modules': sorted(m.split('.')[0] for m in sys.modules),\n"
        "                  'imported': sorted(m for m in sys.modules if m.startswith('sr_imitation.'))}))\n",
        timeout=120,
    )
    assert "torch" in found["modules"]
    probed = {"sr_imitation.io", "sr_imitation.core.sleep", "sr_imitation.infra.fingerprint",
              "sr_imitation.infra.runlog", "sr_imitation.infra.provenance", "sr_imitation.infra.cli_errors",
              "sr_imitation.infra.cli_parsing", "sr_imitation.stream.engine"}
    assert probed <= set(found["imported"])  # the probe did import every layer
    bad = {"lerobot", "metaworld", "mujoco", "gymnasium", "lerobot_policy_act_sr"} & set(found["modules"])
    assert not bad, bad


def test_finding_the_substrates_imports_neither_lerobot_nor_simulators():
    """``sr-train`` imports every substrate folder's ``__init__.py`` to find the one it runs (and the SAC folder's
    own methods): none of them imports LeRobot or a simulator, which only the substrate that runs imports."""
    found = _run_json(
        "import json, sys\n"
        "from sr_imitation.substrates import discover\n"
        "names = sorted(discover())\n"
        "print(json.dumps({'names': names, 'modules': sorted(m.split('.')[0] for m in sys.modules)}))\n",
        timeout=300,
    )
    assert {"act", "sac"} <= set(found["names"])
    bad = {"lerobot", "metaworld", "mujoco", "gymnasium", "lerobot_policy_act_sr"} & set(found["modules"])
    assert not bad, bad


def test_no_top_level_package_shadows_hugging_face_datasets():
    for name in ("datasets", "policies"):
        assert not (ROOT / name / "__init__.py").exists(), f"{name}/ must not be an importable package"
    import datasets  # Hugging Face datasets, which LeRobot imports

    assert Path(datasets.__file__).resolve().parent.parent.name == "site-packages"


def test_rendering_modules_set_up_egl_before_mujoco_loads(monkeypatch):
    """sr_imitation.offscreen is the one place: importing a rendering module without MUJOCO_GL set selects EGL before
    MuJoCo is imported, and a user's own choice is kept."""
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    code = ("import json, os, sys\n"
            "import sr_imitation.envs.needle.rendering, sr_imitation.envs.metaworld.video\n"
            "print(json.dumps({'gl': os.environ.get('MUJOCO_GL'), 'pyopengl': os.environ.get('PYOPENGL_PLATFORM'),\n"
            "                  'mujoco': 'mujoco' in sys.modules}))\n")
    assert _run_json(code, timeout=120) == {"gl": "egl", "pyopengl": "egl", "mujoco": True}
    monkeypatch.setenv("MUJOCO_GL", "glfw")
    kept = _run_json("import json, os\nfrom sr_imitation.offscreen import setup_offscreen_rendering\n"
                     "setup_offscreen_rendering()\nprint(json.dumps({'gl': os.environ['MUJOCO_GL']}))\n", timeout=60)
    assert kept == {"gl": "glfw"}
