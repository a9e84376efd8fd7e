"""The one mp4 writer: frames round-trip through PyAV, files appear only when complete."""

from __future__ import annotations

import av
import numpy as np
import pytest

from sr_imitation.video import Mp4Writer, write_mp4


def test_frames_round_trip_and_the_file_appears_only_when_closed(tmp_path):
    frames = [np.full((48, 64, 3), 20 * i, dtype=np.uint8) for i in range(6)]
    target = tmp_path / "a.mp4"
    with Mp4Writer(target, fps=12.5) as writer:
        for frame in frames[:3]:
            writer.append(frame)
        assert not target.exists()  # only the partial stream (once the encoder flushes) exists before close
        for frame in frames[3:]:
            writer.append(frame)
        writer.close()
    with av.open(str(target)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == 6 and decoded[0].shape == (48, 64, 3)
    assert [int(f.mean()) for f in decoded] == pytest.approx([20 * i for i in range(6)], abs=3)


def test_a_discarded_or_failed_stream_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="even frame sizes"):
        write_mp4(tmp_path / "odd.mp4", [np.zeros((47, 64, 3), np.uint8)])
    with pytest.raises(ValueError, match="no frames"):
        write_mp4(tmp_path / "empty.mp4", [])
    with Mp4Writer(tmp_path / "dropped.mp4", fps=30) as writer:
        writer.append(np.zeros((16, 16, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []
