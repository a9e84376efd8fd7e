"""Write RGB frames to an mp4 with PyAV (bundles its own FFmpeg; torchcodec cannot load here)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import av
import numpy as np


def write_mp4(path: str | Path, frames: Iterable[np.ndarray], fps: int = 30, codec: str = "h264") -> Path:
    """Encode uint8 (H, W, 3) frames (H and W even) to ``path``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = None
        for frame in frames:
            if stream is None:
                h, w = frame.shape[:2]
                if h % 2 or w % 2:
                    raise ValueError(f"mp4 (yuv420p) needs even frame sizes, got {w}x{h}")
                stream = container.add_stream(codec, rate=fps)
                stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
            for packet in stream.encode(
                av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            ):
                container.mux(packet)
        if stream is None:
            raise ValueError("write_mp4 got no frames")
        for packet in stream.encode():
            container.mux(packet)
    return path
