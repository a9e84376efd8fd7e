"""The one mp4 writer: RGB frames streamed to H.264 (yuv420p) with PyAV, which bundles its own FFmpeg (torchcodec
cannot load here). Files appear atomically: frames go to ``.<name>.partial.mp4`` next to the target, renamed into
place when the stream is closed, removed if it is discarded. Used by the needle recorder and main job, the imitation
evaluation videos and the SAC evaluation videos.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np

PARTIAL_VIDEO = r"\..+\.partial\.mp4"
"""The name of a video still being written (``.<name>.partial.mp4``, a regular expression): one found when no
writer holds its folder's lock was left by a killed process."""


class Mp4Writer:
    """Stream frames into ``path`` (see the module docstring); use as a context manager or call :meth:`close`."""

    def __init__(self, path: str | os.PathLike[str], fps: float, codec: str = "h264") -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.partial = self.path.with_name(f".{self.path.stem}.partial.mp4")
        self.fps = Fraction(fps).limit_denominator(1001)
        self.codec = codec
        self.frames = 0
        self._container: Any = av.open(str(self.partial), mode="w")
        self._stream: Any = None

    def append(self, frame: np.ndarray) -> None:
        """Encode one uint8 (H, W, 3) frame; H and W must be even (yuv420p) and equal for every frame."""
        if self._stream is None:
            h, w = frame.shape[:2]
            if h % 2 or w % 2:
                raise ValueError(f"mp4 (yuv420p) needs even frame sizes, got {w}x{h}")
            self._stream = self._container.add_stream(self.codec, rate=self.fps)
            self._stream.width, self._stream.height, self._stream.pix_fmt = w, h, "yuv420p"
        frame_av = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame[..., :3], dtype=np.uint8), format="rgb24")
        for packet in self._stream.encode(frame_av):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> Path:
        """Flush, close and rename into place; returns the final path."""
        if self._stream is None:
            self.discard()
            raise ValueError(f"{self.path}: no frames to write")
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None
        os.replace(self.partial, self.path)
        return self.path

    def discard(self) -> None:
        """Drop the partial file (nothing appears at ``path``)."""
        if self._container is not None:
            self._container.close()
            self._container = None
        self.partial.unlink(missing_ok=True)

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._container is not None:
            self.discard()


def quiet_encoder_logs() -> None:
    """Keep FFmpeg's own messages below errors out of this process's output: libx264 prints about 13 lines of
    statistics for every video it closes (LeRobot's ``encode_video_frames`` does not keep them back), which buried
    ``sr-record --video=true``'s own lines. Errors still print."""
    av.logging.set_level(av.logging.ERROR)
    av.logging.set_libav_level(av.logging.ERROR)  # the native level, used once LeRobot restores the default callback


def write_mp4(path: str | os.PathLike[str], frames: Iterable[np.ndarray], fps: float = 30, codec: str = "h264") -> Path:
    """Encode uint8 (H, W, 3) frames (H and W even) to ``path`` atomically; returns the path."""
    with Mp4Writer(path, fps, codec) as writer:
        for frame in frames:
            writer.append(frame)
        return writer.close()
