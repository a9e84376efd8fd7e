"""A missing FFmpeg is one line: LeRobot's torchcodec warning (about 100 lines of loader errors) cut short."""

from __future__ import annotations

import logging

NOTICE = "torchcodec does not load here (no FFmpeg shared libraries): videos decode with pyav"
"""What the warning becomes."""

LOGGERS = ("lerobot.utils.import_utils", "lerobot.datasets.video_utils")
"""The LeRobot 0.6 loggers that report torchcodec failing to load (and fall back to PyAV themselves)."""


class _DropTorchcodecTracebacks(logging.Filter):
    """Keeps one line of LeRobot's warning that torchcodec does not load (FFmpeg's libraries are missing), once a
    process: LeRobot repeats it for every dataset it opens."""

    said = False

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "torchcodec" in message and "cannot be loaded" in message:
            if _DropTorchcodecTracebacks.said:
                return False
            _DropTorchcodecTracebacks.said = True
            record.msg, record.args = NOTICE, ()
        return True


def quiet_torchcodec() -> None:
    """Make a missing FFmpeg one line instead of a wall of tracebacks: LeRobot's fallback to PyAV stays as it is
    (it decodes the videos), only the message that torchcodec could not load is cut to a line."""
    for name in LOGGERS:
        target = logging.getLogger(name)
        if not any(isinstance(f, _DropTorchcodecTracebacks) for f in target.filters):
            target.addFilter(_DropTorchcodecTracebacks())
