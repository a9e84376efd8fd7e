"""The LeRobot release range: the installed LeRobot lies in the range sr_imitation/lerobot_compat.py was written for,
every name it adapts resolves, no other module imports a name LeRobot moved, and a missing FFmpeg is one line."""

from __future__ import annotations

import ast
import logging
import subprocess
import sys
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.version import Version

from sr_imitation import lerobot_compat
from sr_imitation.infra import torchcodec_notice

ROOT = Path(__file__).resolve().parents[1]

MOVED = {
    "lerobot.datasets.utils": {"dataset_to_policy_features"},
    "lerobot.utils.utils": {"is_torch_device_available"},
    "lerobot.datasets.video_utils": {"get_safe_default_codec"},
    "lerobot.datasets.lerobot_dataset": {"HF_LEROBOT_HOME", "LeRobotDatasetMetadata"},
}
"""Names LeRobot 0.4.4 had where our code imported them from, and 0.6 moved (or removed)."""


def test_the_installed_lerobot_lies_in_the_range_the_compat_module_was_written_for():
    version = Version(lerobot_compat.lerobot_version())
    low, high = (Version(s.lstrip("<>=")) for s in lerobot_compat.SUPPORTED)
    assert low <= version < high, (version, lerobot_compat.SUPPORTED)


def test_pyproject_s_lerobot_range_is_the_compat_module_s():
    for path in (ROOT / "pyproject.toml", *sorted((ROOT / "policies").glob("*/pyproject.toml"))):
        with open(path, "rb") as f:
            deps = [Requirement(d) for d in tomllib.load(f)["project"]["dependencies"]]
        (lerobot,) = [d for d in deps if d.name == "lerobot"]
        assert {"dataset", "training", "viz"} <= lerobot.extras and "metaworld" not in lerobot.extras, path
        assert sorted(str(s) for s in lerobot.specifier) == sorted(lerobot_compat.SUPPORTED), path


def test_every_adapted_name_resolves():
    for name in lerobot_compat.__all__:
        assert getattr(lerobot_compat, name) is not None, name
    assert lerobot_compat.lerobot_home().is_absolute()


def _imports(path: Path) -> set[tuple[str, str]]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            found |= {(node.module, a.name) for a in node.names}
    return found


def test_no_module_but_the_compat_one_imports_a_name_lerobot_moved():
    offenders = []
    for base in (ROOT / "sr_imitation", ROOT / "policies", ROOT / "tools"):
        for path in sorted(base.rglob("*.py")):
            if path.name == "lerobot_compat.py":
                continue
            offenders += [f"{path.relative_to(ROOT)}: {m}.{n}" for m, n in _imports(path) if n in MOVED.get(m, ())]
            text = path.read_text()
            offenders += [f"{path.relative_to(ROOT)}: LeRobotDataset.create" for _ in range(text.count(
                "LeRobotDataset.create("))]
    assert offenders == []


def test_a_dataset_records_with_the_codec_asked_for(tmp_path):
    features = {"observation.images.cam": {"dtype": "video", "shape": (16, 16, 3),
                                           "names": ["height", "width", "channels"]},
                "action": {"dtype": "float32", "shape": (2,), "names": None}}
    dataset = lerobot_compat.create_dataset(vcodec="h264", repo_id="t/x", fps=10, features=features,
                                            root=tmp_path / "x", use_videos=True)
    import numpy as np

    for _ in range(3):
        dataset.add_frame({"observation.images.cam": np.zeros((16, 16, 3), np.uint8),
                           "action": np.zeros(2, np.float32), "task": "t"})
    dataset.save_episode()
    dataset.finalize()
    videos = list((tmp_path / "x" / "videos").rglob("*.mp4"))
    assert len(videos) == 1
    import av

    with av.open(str(videos[0])) as container:
        assert container.streams.video[0].codec_context.name == "h264"


def test_a_missing_ffmpeg_is_one_line_once_a_process(caplog, monkeypatch):
    torchcodec_notice.quiet_torchcodec()
    monkeypatch.setattr(torchcodec_notice._DropTorchcodecTracebacks, "said", False)
    long = "Could not load libtorchcodec. Likely causes:\n" + "\n".join(f"  trace line {i}" for i in range(100))
    with caplog.at_level(logging.WARNING):
        for _ in range(3):  # LeRobot says it for every dataset it opens
            logging.getLogger("lerobot.utils.import_utils").warning(
                f"{long}\n'torchcodec' is installed but cannot be loaded (see the error above). Falling back to "
                "'pyav'.")
        logging.getLogger("lerobot.utils.import_utils").warning("another warning")
    record, other = caplog.records
    assert other.getMessage() == "another warning"
    assert record.getMessage() == torchcodec_notice.NOTICE and "\n" not in record.getMessage()


def test_a_process_that_decodes_a_video_prints_no_wall_of_tracebacks():
    code = ("import logging; logging.basicConfig()\n"
            "import lerobot_policy_act_sr  # what stock lerobot-* scripts import first (plugin discovery)\n"
            "from lerobot.utils.import_utils import get_safe_default_video_backend\n"
            "print(get_safe_default_video_backend())\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip() in {"pyav", "torchcodec"}
    assert len(done.stderr.splitlines()) <= 2, done.stderr[:2000]
