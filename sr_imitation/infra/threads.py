"""A warning when torch's threads will compete with other busy processes for the cores.

torch's CPU kernels split work over ``torch.get_num_threads()`` OpenMP threads and wait for all of them; when other
processes keep the cores busy, each split waits for a descheduled thread. Measured on the 2-core VM (session 30,
docs/RESULTS.md): the CPU main job with torch's default of 2 threads beside one single-thread run took 487 s for its
first wake (102 s with 1 thread beside two runs) and 5.5-7.5 s per sleep iteration (127 ms). Checked once at the start
of a run from the 1-minute load average; only a warning (the thread count is a setting, fingerprinted, and a busy
machine may become idle). Every runner sets its thread count through :func:`set_torch_threads`, which checks.
"""

from __future__ import annotations

import logging
import os

import torch


def oversubscription(threads: int, load: float, cores: int) -> str | None:
    """The warning for ``threads`` torch threads on ``cores`` cores at 1-minute load ``load``, or None: warn when
    more than one thread would share the cores with more than about half a core of other work (our choice)."""
    if threads <= 1 or load + threads <= cores + 0.5:
        return None
    return (f"torch runs {threads} threads on {cores} cores while the machine's load is {load:.1f} (other processes): "
            "multi-threaded torch beside busy cores can run 5-50x slower; give each process its own cores with "
            "torch_threads=1 (sr-train --torch_threads=1, sr-main --train.torch_threads=1) or OMP_NUM_THREADS=1")


def warn_if_oversubscribed(logger: logging.Logger, threads: int) -> str | None:
    """Log :func:`oversubscription`'s warning for this machine now (nothing where the load average is unknown)."""
    try:
        load = os.getloadavg()[0]
    except (OSError, AttributeError):  # not every platform has it
        return None
    message = oversubscription(threads, load, os.cpu_count() or 1)
    if message:
        logger.warning(message)
    return message


def set_torch_threads(threads: int | None, logger: logging.Logger) -> int:
    """Set torch's intra-op threads to ``threads`` (None: keep this process's default, e.g. OMP_NUM_THREADS), warn
    if they would share busy cores (:func:`warn_if_oversubscribed`), and return the number in effect."""
    if threads is not None:
        torch.set_num_threads(threads)
    warn_if_oversubscribed(logger, torch.get_num_threads())
    return torch.get_num_threads()
