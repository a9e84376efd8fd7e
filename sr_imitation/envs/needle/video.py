"""Needle videos use the project's one mp4 writer (:mod:`sr_imitation.video`)."""

from sr_imitation.video import write_mp4

__all__ = ["write_mp4"]
