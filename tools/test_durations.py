"""Write tests/durations.json, the seconds each test file took, from the output of a test run with durations:

    bash .ci/test.sh -q -p no:cacheprovider --durations=0 > /tmp/suite.log 2>&1
    python3 tools/test_durations.py /tmp/suite.log

tests/conftest.py hands the heaviest files to the two pytest workers first (.ci/test.sh: ``--dist loadfile
--no-loadscope-reorder``), so that neither waits alone for a long file at the end. Only the order depends on these
numbers: a stale or missing entry changes how long the suite takes, never what it runs or asserts."""

from __future__ import annotations

import json
import re
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"^([\d.]+)s (?:call|setup|teardown)\s+(tests/\S+?\.py)::")


def file_seconds(log: str) -> dict[str, float]:
    """Seconds per test file: the sum of its tests' set-up, call and teardown phases in pytest's durations report."""
    seconds: Counter[str] = Counter()
    for line in log.splitlines():
        match = LINE.match(line)
        if match:
            seconds[match.group(2)] += float(match.group(1))
    return {name: round(total, 1) for name, total in sorted(seconds.items())}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        sys.stderr.write("usage: python3 tools/test_durations.py <output of a test run with --durations=0>\n")
        return 2
    seconds = file_seconds(Path(argv[0]).read_text())
    if not seconds:
        sys.stderr.write(f"{argv[0]}: no durations report (run the tests with --durations=0)\n")
        return 1
    out = ROOT / "tests" / "durations.json"
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(seconds, indent=1) + "\n")
    tmp.replace(out)
    sys.stdout.write(f"{out}: {len(seconds)} files, {sum(seconds.values()):.0f} s\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
