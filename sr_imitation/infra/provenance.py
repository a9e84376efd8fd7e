"""Which code produced a result: the git commit of the running ``sr_imitation`` checkout.

``results.json`` records it (``code``), so a number in docs/RESULTS.md names its commit from the run itself rather
than from notes. Not a setting (it is not fingerprinted: a resume under a later commit is allowed, and the results
record the commit that wrote them). Substrate-free: the standard library only.
"""

from __future__ import annotations

import functools
import logging
import os
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
"""The directory holding the ``sr_imitation`` package (a git checkout's top level, or site-packages)."""


CODE_PATHS = ("sr_imitation", "policies")
"""The paths of a checkout whose changes count as "dirty" (the code; docs, results and configs do not: configs are
settings, fingerprinted)."""


def code_version(root: Path = PACKAGE_ROOT) -> dict[str, Any]:
    """``{"commit": <40 hex digits>, "dirty": <tracked files under CODE_PATHS differ from it>}`` of the git checkout
    at ``root``; both ``None`` when ``root`` is not the top of a git checkout (an installed wheel) or git is
    unavailable."""
    unknown = {"commit": None, "dirty": None}
    if not (Path(root) / ".git").exists():
        return unknown
    try:
        commit = _git(root, "rev-parse", "HEAD")
        dirty = bool(_git(root, "status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS))
    except (OSError, subprocess.SubprocessError):
        return unknown
    return {"commit": commit, "dirty": dirty}


@functools.lru_cache(maxsize=1)
def process_code_version() -> dict[str, Any]:
    """:func:`code_version` of this package, taken once per process: the stream engine asks at the start of a run,
    so results name the code the process imported even if the checkout moves on while it runs."""
    return code_version()


def log_code_version(logger: logging.Logger) -> dict[str, Any]:
    """Take :func:`process_code_version` at the start of a run (so results.json names the code this process
    imported, not a later checkout) and log it with the CPU (:func:`cpu_signature`); every runner calls this before
    its first phase."""
    code = process_code_version()
    caps = library_caps()
    logger.info("code: commit %s%s; CPU: %s%s", code["commit"] or "unknown (not a git checkout)",
                " with uncommitted changes" if code["dirty"] else "", cpu_signature()["name"],
                "; libraries: " + ", ".join(f"{k}={v}" for k, v in caps.items()) if caps else "")
    return code


LIBRARY_ISA_VARIABLES = ("MKL_ENABLE_INSTRUCTIONS", "MKL_CBWR", "ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA",
                         "OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")
"""Environment variables that make the numerical libraries pick other kernels on the same CPU (MKL behind torch's
Linear, torch's ATen kernels, oneDNN, OpenBLAS and numpy behind numpy), so other floats from the same seed:
tools/experiments/isa_env.sh sets them for queued runs (docs/results/records/sac_sleep.md, 2026-11-30 07:30)."""


def library_caps(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """The :data:`LIBRARY_ISA_VARIABLES` set in ``environ`` (this process's environment by default), by name."""
    env = os.environ if environ is None else environ
    return {k: env[k] for k in LIBRARY_ISA_VARIABLES if env.get(k)}


@functools.lru_cache(maxsize=1)
def cpu_signature() -> dict[str, Any]:
    """The CPU this process computes on, as far as bit-identical results depend on it: ``{"name": <model name,
    family, model, vector extensions>, "avx512": bool}`` from ``/proc/cpuinfo`` (Linux; ``"unknown"`` elsewhere).
    Runs are bit-identical only on one CPU type: an AMD EPYC with AVX-512 and one without give other floats from the
    same seed (docs/RESULTS.md), so results.json records it beside the code's commit."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "cpu family", "model", "flags") and key.strip() not in fields:
                fields[key.strip()] = value.strip()
    except OSError:
        return {"name": "unknown", "avx512": None}
    flags = set(fields.get("flags", "").split())
    vector = [f for f in ("avx512f", "avx2", "fma") if f in flags]
    name = (f"{fields.get('model name', 'unknown')} (family {fields.get('cpu family', '?')}, model "
            f"{fields.get('model', '?')}; {', '.join(vector) or 'no AVX2'})")
    return {"name": name, "avx512": "avx512f" in flags}


def _git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30,
                          check=True).stdout.strip()
