"""``sr-dataset-viz``: LeRobot's own ``lerobot-dataset-viz`` (rerun.io), runnable where torchcodec cannot load.

LeRobot 0.4.4 decodes a dataset's mp4 videos with torchcodec whenever the ``torchcodec`` package is installed
(``lerobot.datasets.video_utils.get_safe_default_codec`` asks only whether it is importable by name), and torchcodec
needs FFmpeg's shared libraries, which this set-up does not provide: ``lerobot-dataset-viz`` on a dataset recorded
with ``--video=true`` stops with "Could not load libtorchcodec". This command runs the same program, same flags,
with PyAV (which bundles its own FFmpeg, as our recorders and training use) as the default decoder when torchcodec
does not load; where it loads, nothing changes. Typical use on a machine without a display::

    sr-dataset-viz --repo-id sr_needle_approach --root datasets/needle_cpu/approach --episode-index 0 \\
        --save 1 --output-dir outputs/viz        # writes an .rrd file: `rerun outputs/viz/<name>.rrd` to look

``sr-dataset-viz --help`` is LeRobot's help. The videos themselves are plain H.264 mp4 files under the dataset's
``videos/`` folder; any video player opens them.
"""

from __future__ import annotations

import logging
import sys

logger = logging.getLogger(__name__)


def torchcodec_loads() -> bool:
    """Whether torchcodec's decoders import (its native libraries load), not only whether the package is there."""
    try:
        import torchcodec.decoders  # noqa: F401, PLC0415
    except Exception:  # noqa: BLE001 (RuntimeError or OSError from the library loader, or ImportError)
        return False
    return True


def use_pyav_unless_torchcodec_loads() -> None:
    """Make LeRobot's datasets default to PyAV when torchcodec does not load (where it loads, nothing changes)."""
    if torchcodec_loads():
        return
    import lerobot.datasets.lerobot_dataset as lerobot_dataset  # noqa: PLC0415
    import lerobot.datasets.video_utils as video_utils  # noqa: PLC0415

    def pyav() -> str:
        return "pyav"

    video_utils.get_safe_default_codec = pyav
    lerobot_dataset.get_safe_default_codec = pyav  # imported by name there
    logger.info("torchcodec does not load here (FFmpeg libraries missing): decoding videos with pyav")


def view_hint(repo_id: str, root: str) -> str:
    """The command that shows the first episode of a recorded dataset (printed by ``sr-record --video=true``)."""
    return (f"view an episode: sr-dataset-viz --repo-id {repo_id} --root {root} --episode-index 0 --save 1 "
            f"--output-dir {root}/viz   (then: rerun {root}/viz/<file>.rrd, or play the mp4 under {root}/videos)")


def entry() -> None:
    """Console script ``sr-dataset-viz``: ``lerobot-dataset-viz`` with PyAV where torchcodec does not load."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    use_pyav_unless_torchcodec_loads()
    from lerobot.scripts.lerobot_dataset_viz import main  # noqa: PLC0415

    sys.argv[0] = "sr-dataset-viz"
    main()


if __name__ == "__main__":
    entry()
