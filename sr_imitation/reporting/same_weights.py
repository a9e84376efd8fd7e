"""Do two runs hold the same files, byte for byte? ``python -m sr_imitation.reporting.same_weights A B``.

Each side is a run folder (its files are hashed) or an archived run (its ``weights.json``, the sealed list of the
weight store's files with their sha256: :mod:`sr_imitation.infra.weight_store`; the store itself need not be on this
machine). The files compared are those matching ``--files`` (fnmatch patterns on the path below the run; default:
every wake's checkpoint and every expert memory, what two runs with the same wakes share). A row per file: ``equal``,
``differs``, or on one side only. Exit 0 when at least one file was compared and every file both sides hold is equal
(with ``--complete=true`` also: neither side holds a matched file the other lacks), 1 otherwise; a folder that is
neither a run nor an archived run, or a ``weights.json`` that does not match its seal, is one line naming it and
exit 2. Reads only; writes nothing.

Protocol W's premise (docs/RESULTS.md, 2026-12-02) is this check between each ``sr_c_b1_pw`` run and the same seed's
archived ``reset_distill`` run: a run in flight can be checked stage by stage, the finished one with ``--complete``.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys
from collections.abc import Sequence
from pathlib import Path

from sr_imitation.infra.weight_store import WEIGHTS_FILE
from sr_imitation.io import file_digest, read_checked_json

WAKES_AND_EXPERTS = ("stages/*/wake/agent.safetensors", "stages/*/expert.safetensors")
"""The default ``--files``: each wake's checkpoint and each expert memory (``stages/<k>_<skill>/...``)."""


def digests(side: Path, patterns: Sequence[str] = WAKES_AND_EXPERTS) -> dict[str, str]:
    """``{path below the run: sha256}`` of the files matching ``patterns``: from ``side/weights.json`` when the
    folder has one (an archived run), else by hashing the run folder's files."""
    side = Path(side)
    if not side.is_dir():
        raise FileNotFoundError(f"{side}: no such folder")
    if (side / WEIGHTS_FILE).is_file():
        listed = {path: entry["sha256"] for path, entry in read_checked_json(side / WEIGHTS_FILE)["files"].items()}
    elif (side / "stages").is_dir():
        listed = {p.relative_to(side).as_posix(): "" for p in (side / "stages").rglob("*") if p.is_file()}
    else:
        raise FileNotFoundError(f"{side}: neither a run folder (no stages/) nor an archived run (no {WEIGHTS_FILE})")
    chosen = {path: sha for path, sha in listed.items() if any(fnmatch.fnmatchcase(path, p) for p in patterns)}
    return {path: sha or file_digest(side / path) for path, sha in sorted(chosen.items())}


def same_files(a: Path, b: Path, patterns: Sequence[str] = WAKES_AND_EXPERTS) -> dict[str, str]:
    """``{path: "equal" | "differs" | "only in A" | "only in B"}`` over the files matching ``patterns``."""
    da, db = digests(a, patterns), digests(b, patterns)
    rows = {}
    for path in sorted(set(da) | set(db)):
        if path not in db:
            rows[path] = "only in A"
        elif path not in da:
            rows[path] = "only in B"
        else:
            rows[path] = "equal" if da[path] == db[path] else "differs"
    return rows


def verdict(rows: dict[str, str], complete: bool = False) -> bool:
    """True when at least one file was compared, every compared file is equal and (``complete``) none is one-sided."""
    compared = [state for state in rows.values() if state in ("equal", "differs")]
    one_sided = len(rows) - len(compared)
    return bool(compared) and all(state == "equal" for state in compared) and not (complete and one_sided)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path, help="a run folder or an archived run (with weights.json)")
    parser.add_argument("b", type=Path, help="the same, the other side")
    parser.add_argument("--files", default=",".join(WAKES_AND_EXPERTS),
                        help="comma-separated fnmatch patterns on the path below the run (default: %(default)s)")
    parser.add_argument("--complete", default="false", choices=("true", "false"),
                        help="also fail when a matched file is on one side only")
    args = parser.parse_args(argv)
    patterns = [p.strip() for p in args.files.strip("[]").split(",") if p.strip()]
    rows = same_files(args.a, args.b, patterns)
    width = max((len(p) for p in rows), default=0)
    ok = verdict(rows, args.complete == "true")
    counts = {state: list(rows.values()).count(state) for state in ("equal", "differs", "only in A", "only in B")}
    print("".join(f"{path:<{width}}  {state}\n" for path, state in rows.items())  # noqa: T201 (command output)
          + f"A = {args.a}, B = {args.b}: " + ", ".join(f"{n} {state}" for state, n in counts.items())
          + (": the same" if ok else ": NOT the same"))
    return 0 if ok else 1


if __name__ == "__main__":
    from sr_imitation.infra.cli_errors import run_cli

    sys.exit(run_cli("sr_imitation.reporting.same_weights", main))
