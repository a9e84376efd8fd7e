"""``--overwrite`` never deletes what a user owns, on the engine's toy substrate (seconds): only a directory
recognised as a run is replaced, only through a rename that a failed start undoes, never one that is, holds or
lies inside an input; a directory holding only a killed start's temporary fingerprint holds no run.

Before: the run directory was removed with ``shutil.rmtree`` before anything was checked, whatever it held (a
folder with only ``thesis.txt``: one warning, rc 0, the file gone)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.infra.fingerprint import FINGERPRINT_FILE, settings_fingerprint
from sr_imitation.stream import RunDirectory, StreamEngine, make_method
from sr_imitation.stream.rundir import REPLACED_MARK, OverwriteRefusedError
from tests.stream.toy import ToySubstrate
from tests.stream.wiring import same

SKILLS = ["a", "b"]
TOY_ENTRIES = ("stage*",)
"""What the toy substrate writes at a run's top level."""


def engine(out: Path, *, overwrite: bool = False, resume: bool = False, inputs: tuple[Path, ...] = (),
           substrate: ToySubstrate | None = None, **settings: Any) -> StreamEngine:
    substrate = substrate or ToySubstrate(out, SKILLS, wake_steps=5, sleep_iterations=3)
    config = {"method": "sr", "skills": SKILLS, **settings}
    run = RunDirectory(out, settings_fingerprint(config), "config.json", config, resume=resume, overwrite=overwrite,
                       inputs=inputs, entries=TOY_ENTRIES)
    return StreamEngine(substrate, make_method("sr", substrate, substrate.method_settings()), run, progress=False)


def tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def no_sibling(parent: Path) -> bool:
    return not [p for p in parent.iterdir() if REPLACED_MARK in p.name]


def test_overwrite_replaces_a_run_and_keeps_nothing_aside(tmp_path):
    out = tmp_path / "run"
    first = engine(out).run()
    again = engine(out, overwrite=True).run()
    assert again["evals"] == first["evals"] and same(again["weights"], first["weights"])
    assert no_sibling(tmp_path)


def test_overwrite_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    out = tmp_path / "thesis"
    out.mkdir()
    (out / "thesis.txt").write_text("four years")
    with pytest.raises(OverwriteRefusedError, match=r"thesis: --overwrite=true refused: it holds no settings_fin"):
        engine(out, overwrite=True).run()
    assert tree(out) == {"thesis.txt": b"four years"} and no_sibling(tmp_path)
    # through a command: one line naming the folder, exit status 2, no traceback
    with pytest.raises(SystemExit) as exc:
        run_cli("sr-train", lambda argv: engine(out, overwrite=True).run(), [])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and "Traceback" not in err[0]


def test_overwrite_refuses_a_run_holding_foreign_files(tmp_path):
    out = tmp_path / "run"
    engine(out).run()
    (out / "notes.txt").write_text("mine")
    before = tree(out)
    with pytest.raises(OverwriteRefusedError, match=r"it holds notes.txt, which no run writes"):
        engine(out, overwrite=True).run()
    assert tree(out) == before and no_sibling(tmp_path)


def test_overwrite_never_removes_an_input_or_a_folder_holding_one(tmp_path):
    data = tmp_path / "data"
    (data / "skill_a").mkdir(parents=True)
    (data / "skill_a" / "episode.parquet").write_bytes(b"demos")
    before = tree(data)
    for out in (data, tmp_path):  # the input itself, and a folder above it
        with pytest.raises(OverwriteRefusedError, match="refused: it holds the input"):
            engine(out, overwrite=True, inputs=(data / "skill_a",)).run()
        assert tree(data) == before
    # a run inside its own input would change the data it records the identity of
    with pytest.raises(OverwriteRefusedError, match="lies inside the input"):
        engine(data / "skill_a" / "run", inputs=(data / "skill_a",)).run()
    assert tree(data) == before


def test_a_failed_start_restores_the_replaced_run(tmp_path):
    out = tmp_path / "run"
    engine(out).run()
    before = tree(out)

    class BrokenSubstrate(ToySubstrate):
        def setup(self) -> None:
            raise RuntimeError("the new run cannot start")

    broken = BrokenSubstrate(out, SKILLS, wake_steps=5, sleep_iterations=3)
    with pytest.raises(RuntimeError, match="cannot start"):
        engine(out, overwrite=True, substrate=broken).run()
    assert tree(out) == before and no_sibling(tmp_path)


def test_a_killed_start_left_only_a_temporary_fingerprint_so_a_plain_rerun_proceeds(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / f".{FINGERPRINT_FILE}.k2j4.tmp").write_text('{"format": "sr_imitation.settings_fin')
    assert not RunDirectory.occupied(out)
    with pytest.raises(FileNotFoundError, match="holds no run"):
        engine(out, resume=True).run()
    engine(out).run()
    assert (out / FINGERPRINT_FILE).is_file() and not list(out.glob(".*.tmp"))


def test_a_run_set_aside_by_a_killed_overwrite_start_is_kept_and_named_at_the_next_start(tmp_path, caplog):
    out = tmp_path / "run"
    engine(out).run()
    before = tree(out)
    aside = tmp_path / f".run{REPLACED_MARK}20261127-010000-4242"
    out.rename(aside)  # what a start killed between its rename and its first phase leaves
    with caplog.at_level("WARNING", logger="sr_imitation.stream.rundir"):
        engine(out).run()
    assert tree(aside) == before  # kept, never deleted by the next start
    warned = [r.getMessage() for r in caplog.records if "set aside" in r.getMessage()]
    assert len(warned) == 1 and str(aside) in warned[0] and "rename it back to run" in warned[0]
