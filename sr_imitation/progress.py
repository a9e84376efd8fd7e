"""Progress on long work: a bar on a terminal, a log line every minute anywhere else.

A stream runs for minutes (the state-only preset) to hours (the vision preset, about 2 h on one CPU core), most
often under ``nohup``, a scheduler or CI, with its standard error in a file. A tqdm bar there is a carriage-return
redraw every 0.1 s: a two-hour vision run left 1.5 MB of redraws and not one readable line. So :class:`Progress` is
a tqdm bar when standard error is a terminal (or a Jupyter kernel) and otherwise a log line at most every
``EVERY_S`` seconds (our choice: 60), each with the count, the elapsed time, the estimated time left and the loop's
latest values::

    ... INFO sr_imitation.core.sleep: sleep k=3: 412/1000 (41%), 1m00s elapsed, ~1m26s left; obj=0.0123, worst=0.045

``SR_PROGRESS=bar`` or ``SR_PROGRESS=log`` forces either form. The lowest layer with :mod:`sr_imitation.io`: it
imports nothing of the package, so the core's sleep loop can use it.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import Any

from tqdm.auto import tqdm

EVERY_S = 60.0
"""Seconds between two progress log lines at least (our choice: a line a minute)."""

PROGRESS_ENV = "SR_PROGRESS"
"""``bar`` or ``log`` forces the form of every progress display; unset: a bar on a terminal, log lines elsewhere."""


def interactive() -> bool:
    """Whether progress should be a bar: standard error is a terminal or this is a Jupyter kernel."""
    forced = os.environ.get(PROGRESS_ENV, "").strip().lower()
    if forced in ("bar", "log"):
        return forced == "bar"
    if "ipykernel" in sys.modules:
        return True
    stream = sys.stderr
    return bool(stream is not None and hasattr(stream, "isatty") and stream.isatty())


def format_duration(seconds: float) -> str:
    """``1h05m``, ``3m07s``, ``42s``: a duration as the progress lines write it."""
    seconds = max(0, int(round(seconds)))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours}h{minutes:02d}m"
    return f"{minutes}m{secs:02d}s" if minutes else f"{secs}s"


class Progress:
    """Count ``total`` units of one loop: a tqdm bar (interactive) or periodic log lines on ``logger``.

    Args:
        total: the loop's planned length (a loop may stop earlier: early stopping, a plateau).
        desc: what is counted, e.g. ``"wake approach"``, ``"sleep k=3"``.
        logger: where the lines go (the calling module's logger).
        enabled: ``False`` shows nothing either way (the ``progress=False`` of the library's functions).
        every_s: seconds between two log lines at least; default :data:`EVERY_S`.
        unit: tqdm's unit name.
        initial: steps already done before this bar (a resumed loop): counted as done, left out of the time
            estimate, which extrapolates from the steps this bar has seen.
    """

    def __init__(self, total: int, desc: str, logger: logging.Logger, enabled: bool = True,
                 every_s: float | None = None, unit: str = "it", initial: int = 0) -> None:
        self.total, self.desc, self.logger = int(total), desc, logger
        self.every_s = EVERY_S if every_s is None else float(every_s)
        self.n = self.initial = int(initial)
        self.postfix: dict[str, Any] = {}
        self.bar = (tqdm(total=total, initial=self.initial, desc=desc, unit=unit, leave=False)
                    if enabled and interactive() else None)
        self.logs = enabled and self.bar is None
        self.start = self.last = time.monotonic()

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.bar is not None:
            self.bar.update(n)
        elif self.logs and time.monotonic() - self.last >= self.every_s:
            self.log()

    def set_postfix(self, **values: Any) -> None:
        """The loop's latest values, shown on the bar and in the next log line."""
        self.postfix = values
        if self.bar is not None:
            self.bar.set_postfix(values)

    def log(self) -> None:
        """Write one progress line now (log form only)."""
        now = time.monotonic()
        self.last = now
        elapsed = now - self.start
        share = self.n / self.total if self.total > 0 else 0.0
        done = (self.n - self.initial) / (self.total - self.initial) if self.total > self.initial else 0.0
        left = f", ~{format_duration(elapsed * (1 - done) / done)} left" if 0 < done < 1 else ""
        values = "; " + ", ".join(f"{k}={v}" for k, v in self.postfix.items()) if self.postfix else ""
        self.logger.info("%s: %d/%d (%.0f%%), %s elapsed%s%s", self.desc, self.n, self.total, 100 * share,
                         format_duration(elapsed), left, values)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
