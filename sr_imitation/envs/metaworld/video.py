"""Offscreen rollout videos of Meta-World skills (EGL by default; shadows, reflections and multisampling off).

:class:`SkillRenderer` draws RGB frames of a :class:`~sr_imitation.envs.metaworld.tasks.SkillEnv` from one of
Meta-World's fixed cameras with its own ``mujoco.Renderer``; it only reads the simulation state, so recording never
changes a rollout. :class:`VideoWriter` streams frames to an mp4 under a temporary name and renames it once the
outcome is known (``<skill>_episode<i>_<success|failure>.mp4``, the imitation substrate's naming).

Meta-World's ``corner*`` cameras are defined with their image "up" axis pointing at the floor, so raw frames come
out upside down; frames from such cameras are rotated by 180 degrees (a rotation, not a mirror).
"""

from __future__ import annotations

import os

from sr_imitation.offscreen import setup_offscreen_rendering

setup_offscreen_rendering()  # must precede the first `import mujoco` to take effect

import functools  # noqa: E402
import logging  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import TYPE_CHECKING, Any  # noqa: E402

import numpy as np  # noqa: E402

if TYPE_CHECKING:
    from sr_imitation.envs.metaworld.tasks import SkillEnv

logger = logging.getLogger(__name__)

CAMERAS: tuple[str, ...] = ("corner", "corner2", "corner3", "corner4", "topview", "behindGripper", "gripperPOV")
"""Cameras of Meta-World v3's Sawyer scene (``assets/objects/assets/xyz_base.xml``)."""
DEFAULT_CAMERA = "corner2"
"""A fixed three-quarter view from above the table: robot, object and goal all in frame for the MT5/MT8 skills."""
MIN_SIZE, MAX_SIZE, MACRO_BLOCK = 16, 2048, 16
"""Frame size limits; both sides must be multiples of 16 (otherwise the H.264 writer silently rescales)."""


def check_video_size(height: int, width: int) -> None:
    """Raise ``ValueError`` unless ``height`` x ``width`` is a valid video frame size."""
    for name, value in (("video_height", height), ("video_width", width)):
        if not isinstance(value, int) or not MIN_SIZE <= value <= MAX_SIZE or value % MACRO_BLOCK:
            raise ValueError(f"{name} must be a multiple of {MACRO_BLOCK} in [{MIN_SIZE}, {MAX_SIZE}], got {value!r}")


def check_video_settings(episodes: int, height: int, width: int, camera: str) -> None:
    """Raise ``ValueError`` naming the setting (``videos_per_skill``, ``video_height``, ...) that is invalid."""
    if not isinstance(episodes, int) or episodes < 0:
        raise ValueError(f"videos_per_skill must be an integer >= 0 (0 disables videos), got {episodes!r}")
    check_video_size(height, width)
    if camera not in CAMERAS:
        raise ValueError(f"video_camera must be one of {CAMERAS}, got {camera!r}")


@dataclass(frozen=True)
class VideoSpec:
    """Which evaluation episodes to record and how: the first ``episodes`` episodes of a rollout into
    ``directory``."""

    directory: Path
    episodes: int = 1
    height: int = 240
    width: int = 320
    camera: str = DEFAULT_CAMERA

    def __post_init__(self) -> None:
        object.__setattr__(self, "directory", Path(self.directory))
        check_video_settings(self.episodes, self.height, self.width, self.camera)


class SkillRenderer:
    """RGB uint8 (height, width, 3) frames of ``env``'s current state from ``camera``; call :meth:`close`."""

    def __init__(self, env: SkillEnv, height: int = 240, width: int = 320, camera: str = DEFAULT_CAMERA) -> None:
        import mujoco

        check_video_size(height, width)
        model, data = env.mj_model, env.mj_data
        self._camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self._camera_id < 0:
            raise ValueError(f"{env.skill} has no camera {camera!r}")
        self._data = data
        # visual-only model settings (no effect on physics), read once when the GL context is created:
        # no multisampling (MSAA costs ~10-100x on CPU-EGL) and a framebuffer large enough for the frame size
        quality, glob = model.vis.quality, model.vis.global_
        saved = (quality.offsamples, glob.offwidth, glob.offheight)
        quality.offsamples = 0
        glob.offwidth, glob.offheight = max(glob.offwidth, width), max(glob.offheight, height)
        try:
            self._renderer = mujoco.Renderer(model, height=height, width=width)
        finally:
            quality.offsamples, glob.offwidth, glob.offheight = saved
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._camera = camera
        self._flip: bool | None = None

    def frame(self) -> np.ndarray:
        """The current scene as seen from the camera (upright)."""
        if self._renderer is None:
            raise RuntimeError("frame() called after close()")
        if self._flip is None:  # the camera's image "up" (its y axis) in world coordinates points down
            self._flip = bool(self._data.cam_xmat[self._camera_id].reshape(3, 3)[2, 1] < 0)
        self._renderer.update_scene(self._data, camera=self._camera)
        img = self._renderer.render()
        return np.ascontiguousarray(img[::-1, ::-1]) if self._flip else img

    def close(self) -> None:
        """Free the GL context (EGL complains at interpreter exit about contexts left open)."""
        if getattr(self, "_renderer", None) is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> SkillRenderer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class VideoWriter:
    """Streams frames into ``<directory>/.<stem>.partial.mp4`` (the project's one writer, :mod:`sr_imitation.video`);
    :meth:`finish` renames it to ``<stem>_<suffix>.mp4``.

    Frames are encoded as they arrive (no episode-length buffer in memory). :meth:`discard` (or leaving the
    ``with`` block without :meth:`finish`) removes the partial file.
    """

    def __init__(self, directory: Path, stem: str, fps: float) -> None:
        from sr_imitation.video import Mp4Writer

        self.directory = Path(directory)
        self.stem = stem
        self._writer: Any = Mp4Writer(self.directory / f"{stem}.mp4", fps)
        self.frames = 0

    def append(self, frame: np.ndarray) -> None:
        self._writer.append(frame)
        self.frames += 1

    def finish(self, suffix: str) -> Path:
        """Close the stream and move it to its final name; returns the path."""
        written = self._writer.close()
        self._writer = None
        path = self.directory / f"{self.stem}_{suffix}.mp4"
        os.replace(written, path)
        logger.debug("wrote %s (%d frames)", path, self.frames)
        return path

    def discard(self) -> None:
        if self._writer is not None:
            self._writer.discard()
            self._writer = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.discard()


@functools.cache
def rendering_unavailable() -> str | None:
    """``None`` if offscreen rendering works in this process, else the reason (e.g. no EGL); never raises."""
    try:
        import mujoco

        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='0.1'/></worldbody></mujoco>")
        with mujoco.Renderer(model, height=MIN_SIZE, width=MIN_SIZE) as renderer:
            renderer.update_scene(mujoco.MjData(model))
            renderer.render()
    except Exception as exc:  # noqa: BLE001 (any failure to get a GL context means "no videos", not a crash)
        return f"{type(exc).__name__}: {exc}"
    return None
