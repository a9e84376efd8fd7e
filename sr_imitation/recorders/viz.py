"""How to look at a recorded video dataset: LeRobot's own ``lerobot-dataset-viz`` (rerun.io), output beside it.

LeRobot 0.6 decodes with PyAV by itself where torchcodec cannot load (no FFmpeg shared libraries here), so the stock
command works on the datasets ``sr-record --video=true`` writes (0.4.4 needed our ``sr-dataset-viz``, now gone).
The recording goes to ``<dataset>_viz`` beside the dataset, never inside it: a file inside would change the
dataset's content digest, and runs on it would be refused as "dataset differs".
"""

from __future__ import annotations

import shlex
from pathlib import Path


def viz_folder(root: str | Path) -> Path:
    """Where the hint writes its rerun recording: ``<dataset>_viz``, a sibling of the dataset folder."""
    root = Path(root)
    return root.with_name(f"{root.name}_viz")


def view_hint(repo_id: str, root: str | Path) -> str:
    """The command that shows the first episode of a recorded dataset (printed by ``sr-record --video=true``),
    shell-quoted so that it can be pasted as it is, whatever the path holds."""
    out = viz_folder(root)
    command = shlex.join(["lerobot-dataset-viz", "--repo-id", repo_id, "--root", str(root), "--episode-index", "0",
                          "--save", "1", "--output-dir", str(out)])
    return (f"view an episode: {command}   (then: rerun {shlex.quote(str(out))}/<file>.rrd, or play the mp4 under "
            f"{shlex.quote(str(Path(root) / 'videos'))})")
