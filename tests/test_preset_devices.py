"""What the documents say about a preset's device agrees with the preset's file and with docs/BENCHMARKS.md.

A preset whose file sets ``"device": "cpu"`` is never said to need a GPU (README once said the SAC paper preset
"needs a GPU" while its file sets ``"device": "cpu"`` and BENCHMARKS measured that a GPU does not buy SAC updates);
every configs/README.md row that speaks of a GPU states the file's device. A sentence is about the presets it names,
or, naming none, about the last one named before it in its paragraph."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "configs/README.md", *(f"docs/{name}" for name in (
    "COMMANDS.md", "ARCHITECTURE.md", "BENCHMARKS.md", "EVIDENCE.md", "NEEDLE_ENV.md")), "policies/README.md"]
"""The user-facing pages (the dated records, docs/RESULTS.md and docs/results/, keep what was said when)."""
NEEDS_A_GPU = re.compile(r"\b(?:needs?|requires?|meant for|calls? for|only on) (?:a |one |the )?GPUs?\b", re.I)
PRESET = re.compile(r"\b(\w+)\.json\b")


def preset_devices() -> dict[str, str | None]:
    """Each preset's device (``policy.device``, ``train.policy.device`` or ``device``), None where the file has none."""
    devices = {}
    for path in sorted((ROOT / "configs").glob("*.json")):
        data = json.loads(path.read_text())
        train = data.get("train", data)
        devices[path.stem] = train.get("policy", {}).get("device", train.get("device"))
    return devices


def gpu_claims_about_cpu_presets(text: str, devices: dict[str, str | None]) -> list[str]:
    """The sentences of ``text`` that say a GPU is needed about presets whose files all set ``"device": "cpu"``."""
    found = []
    for paragraph in re.split(r"\n\s*\n|\n(?=\|)", text):
        last: list[str] = []
        for sentence in re.split(r"(?<=[.!?])\s+(?=[A-Z`*(])|\s\|\s", " ".join(paragraph.split())):
            named = [name for name in PRESET.findall(sentence) if name in devices]
            last = named or last
            if NEEDS_A_GPU.search(sentence) and last and all(devices[name] == "cpu" for name in last):
                found.append(sentence)
    return found


def test_no_page_says_a_cpu_preset_needs_a_gpu():
    devices = preset_devices()
    assert devices["sac_mt5_paper"] == "cpu" and devices["needle_paper"] is None  # the two the pages discuss
    for page in PAGES:
        assert gpu_claims_about_cpu_presets((ROOT / page).read_text(), devices) == [], page


def test_the_check_finds_the_sentence_readme_once_had():
    devices = {"sac_mt5_paper": "cpu", "needle_paper": None}
    said = ("**Paper preset** (`configs/sac_mt5_paper.json`): every value of the appendix tables. One update takes "
            "~15 ms on one CPU core, so its millions of environment steps need a GPU.")
    assert gpu_claims_about_cpu_presets(said, devices) == ["One update takes ~15 ms on one CPU core, so its millions "
                                                           "of environment steps need a GPU."]
    assert gpu_claims_about_cpu_presets("`needle_paper.json`: the camera; meant for a GPU.", devices) == []


def test_every_preset_has_a_row_and_a_row_about_a_gpu_states_the_files_device():
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `(\w+)\.json` \|.*$", (ROOT / "configs" / "README.md")
                                                          .read_text(), re.M)}
    devices = preset_devices()
    assert sorted(rows) == sorted(devices)
    for name, row in rows.items():
        if "GPU" in row:
            stated = f'`"device": "{devices[name]}"`' if devices[name] else "no `device` in the file"
            assert stated in row, (name, stated)


def test_benchmarks_still_measures_what_the_sac_preset_s_device_rests_on():
    benchmarks = " ".join((ROOT / "docs" / "BENCHMARKS.md").read_text().split())
    commands = " ".join((ROOT / "docs" / "COMMANDS.md").read_text().split())
    assert "a GPU does not buy SAC updates" in benchmarks
    assert 'sets `"device": "cpu"`' in commands and "a GPU does not buy SAC updates" in commands
