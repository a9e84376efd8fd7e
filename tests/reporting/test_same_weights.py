"""``sr_imitation.reporting.same_weights``: two runs' wake checkpoints and expert memories, byte for byte, whether a
side is a run folder or an archived run's ``weights.json`` (protocol W's premise)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from sr_imitation.infra.weight_store import WEIGHTS_FILE, store_weights
from sr_imitation.io import write_checked_json
from sr_imitation.reporting.same_weights import main, same_files, verdict


def _run(root, stages: dict[str, bytes]):
    """A run folder: per stage a wake checkpoint, an expert memory and a sleep checkpoint (not compared)."""
    for stage, content in stages.items():
        (root / "stages" / stage / "wake").mkdir(parents=True)
        (root / "stages" / stage / "sleep").mkdir(parents=True)
        (root / "stages" / stage / "wake" / "agent.safetensors").write_bytes(b"wake" + content)
        (root / "stages" / stage / "expert.safetensors").write_bytes(b"expert" + content)
        (root / "stages" / stage / "sleep" / "agent.safetensors").write_bytes(b"sleep" + stage.encode())
    return root


def _archived(tmp_path, run, name):
    """The run as an archive holds it: only its sealed weights.json (the store may be on another machine)."""
    archived = tmp_path / "archive" / name
    archived.mkdir(parents=True)
    write_checked_json(archived / WEIGHTS_FILE, store_weights(run, tmp_path / "archive.weights" / name))
    return archived


def test_a_run_in_flight_against_an_archived_run(tmp_path, capsys):
    full = _run(tmp_path / "rd", {"01_reach": b"1", "02_door-open": b"2"})
    archived = _archived(tmp_path, full, "rd_seed0")
    flight = _run(tmp_path / "pw", {"01_reach": b"1"})  # the same first stage, the second not written yet
    rows = same_files(flight, archived)
    assert rows == {"stages/01_reach/expert.safetensors": "equal", "stages/01_reach/wake/agent.safetensors": "equal",
                    "stages/02_door-open/expert.safetensors": "only in B",
                    "stages/02_door-open/wake/agent.safetensors": "only in B"}
    assert verdict(rows) and not verdict(rows, complete=True)
    assert main([str(flight), str(archived)]) == 0
    assert main([str(flight), str(archived), "--complete=true"]) == 1
    assert "2 equal, 0 differs, 0 only in A, 2 only in B: the same" in capsys.readouterr().out


def test_one_differing_byte_is_found_and_the_sleep_is_not_compared(tmp_path, capsys):
    a = _run(tmp_path / "a", {"01_reach": b"1", "02_door-open": b"2"})
    b = _run(tmp_path / "b", {"01_reach": b"1", "02_door-open": b"X"})
    (b / "stages" / "01_reach" / "sleep" / "agent.safetensors").write_bytes(b"another sleep")
    rows = same_files(a, b)
    assert [p for p, s in rows.items() if s == "differs"] == ["stages/02_door-open/expert.safetensors",
                                                              "stages/02_door-open/wake/agent.safetensors"]
    assert main([str(a), str(b)]) == 1 and "NOT the same" in capsys.readouterr().out
    only_reach = "stages/01_*/wake/agent.safetensors,stages/01_*/expert.safetensors"
    assert main([str(a), str(b), f"--files={only_reach}", "--complete=true"]) == 0
    sleeps = "stages/*/sleep/agent.safetensors"
    assert main([str(a), str(b), f"--files={sleeps}"]) == 1


def test_nothing_compared_is_not_the_same(tmp_path):
    a = _run(tmp_path / "a", {"01_reach": b"1"})
    b = _run(tmp_path / "b", {})
    (b / "stages").mkdir(parents=True)
    assert not verdict(same_files(a, b))


@pytest.mark.parametrize("broken", ["not a run", "edited listing"])
def test_a_user_error_is_one_line_naming_the_folder_or_file(tmp_path, broken):
    run = _run(tmp_path / "rd", {"01_reach": b"1"})
    other = _archived(tmp_path, run, "rd_seed0")
    if broken == "not a run":
        other = tmp_path / "empty"
        other.mkdir()
    else:
        listing = json.loads((other / WEIGHTS_FILE).read_text())
        listing["files"]["stages/01_reach/expert.safetensors"]["sha256"] = "0" * 64
        (other / WEIGHTS_FILE).write_text(json.dumps(listing))
    done = subprocess.run([sys.executable, "-m", "sr_imitation.reporting.same_weights", str(run), str(other)],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 2 and not done.stdout
    assert len(done.stderr.strip().splitlines()) == 1 and str(other) in done.stderr, done.stderr
