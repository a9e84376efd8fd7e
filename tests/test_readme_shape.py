"""README is a guide a newcomer reads in five minutes (issue 90): at most 250 lines and 2,500 words, a runnable command
within its first 40 lines, "Which method where" one table of at most six rows and at most three sentences, every
number in it one the evidence page states (whose numbers tests/test_results_doc.py recomputes), every link alive."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_readme_is_short_and_starts_with_something_to_run():
    lines = README.splitlines()
    assert len(lines) <= 250 and len(README.split()) <= 2500, (len(lines), len(README.split()))
    assert lines.index("```bash") < 40
    assert "Python 3.12" in README and "LeRobot 0.6" in README  # what it needs, said up front


def test_which_method_where_is_one_small_table_whose_numbers_the_evidence_states():
    section = README.split("## Which method where", 1)[1].split("\n## ", 1)[0].strip()
    table = [line for line in section.splitlines() if line.startswith("| ")]
    prose = " ".join(line for line in section.splitlines() if line and not line.startswith("|"))
    assert 1 <= len(table) - 1 <= 6  # the header, then at most six streams
    assert len(re.findall(r"[.!?](?:\s|$)", prose)) <= 3
    evidence = " ".join((ROOT / "docs" / "EVIDENCE.md").read_text().split())
    numbers = set(re.findall(r"(?<![\w.])\d+\.\d+(?: \+- \d+\.\d+)?", " ".join(table)))
    assert len(numbers) >= 12 and sorted(n for n in numbers if n not in evidence) == []


def test_every_relative_link_of_readme_resolves():
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README):
        assert (ROOT / target).exists(), target
    for page, anchor in re.findall(r"\((docs/[\w/]+\.md)#([^)]+)\)", README):  # RESULTS' sections, a record's
        anchors = {re.sub(r"[^\w\- ]", "", h.lstrip("#").strip().lower()).replace(" ", "-")
                   for h in (ROOT / page).read_text().splitlines() if h.startswith("#")}
        assert anchor in anchors, (page, anchor)
