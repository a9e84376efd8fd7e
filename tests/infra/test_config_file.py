"""The ``--config_path`` file is read once a command, by one function, and draccus is handed its settings."""

from __future__ import annotations

import builtins
import io
import json
import re
from pathlib import Path

import pytest

from sr_imitation.infra.config_file import ConfigFile, config_file, config_scope, read_config_file
from sr_imitation.io import CorruptFileError, write_checked_json

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def opened(monkeypatch):
    """Every file opened for reading while the test runs (``open``, ``io.open``: ``Path.read_text`` and draccus
    included)."""
    paths: list[Path] = []
    real = builtins.open

    def recording(file, *args, **kwargs):
        mode = args[0] if args else kwargs.get("mode", "r")
        if isinstance(file, (str, Path)) and not set(mode) & set("wax+"):
            paths.append(Path(file).resolve())
        return real(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", recording)
    monkeypatch.setattr(io, "open", recording)
    return paths


@pytest.mark.parametrize("preset", ["needle_cpu.json", "sac_mt5_cpu.json", "needle_cpu_m16.json"])
def test_sr_train_opens_its_config_file_once(preset, opened):
    from sr_imitation import cli

    path = REPO / "configs" / preset
    cli.parse_args([f"--config_path={path}", "--seed=3"])
    assert opened.count(path.resolve()) == 1


def test_a_whole_run_opens_its_config_file_once_and_a_resume_its_run_s_file(tmp_path, sr_train, opened):
    preset = tmp_path / "preset.json"
    preset.write_text(json.dumps({"substrate": "toy", "stream": {"skills": ["a", "b"]}, "progress": False}))
    sr_train([f"--config_path={preset}", f"--output_dir={tmp_path / 'run'}"])
    assert opened.count(preset.resolve()) == 1
    from sr_imitation import cli

    stored = (tmp_path / "run" / "train_config.json").resolve()
    opened.clear()
    assert cli.parse_args([f"--config_path={stored}", "--resume=true"]).output_dir == tmp_path / "run"
    assert opened.count(stored) == 1


def test_one_function_reads_config_files():
    """The source: ``--config_path`` files are parsed by :func:`read_config_file` alone; draccus is never given a
    path (``ArgumentParser(..., config_path=...)``) and no command module parses JSON of its own for the flags."""
    readers = []
    for path in sorted((REPO / "sr_imitation").rglob("*.py")):
        text = path.read_text()
        if re.search(r"ArgumentParser\([^)]*config_path=(?!None)", text) or "draccus.parse(" in text and \
                "config_path=" in text:
            readers.append(path.relative_to(REPO).as_posix())
    assert readers == []
    cli_modules = ["sr_imitation/cli.py", "sr_imitation/main_job.py", "sr_imitation/infra/cli_parsing.py",
                   "sr_imitation/substrates/act/cli.py", "sr_imitation/substrates/sac/cli.py"]
    for rel in cli_modules:
        text = (REPO / rel).read_text()
        assert "json.load" not in text and "read_text(" not in text, rel
    grid = (REPO / "sr_imitation/experiments/grid.py").read_text()  # sr-grid's --preset: the same reader
    preset_reader = grid.split("def substrate_of_preset", 1)[1].split("\ndef ", 1)[0]
    assert "read_config_file(preset)" in preset_reader and "json.load" not in preset_reader


def test_the_reader_names_the_file_in_one_line(tmp_path):
    missing = tmp_path / "missing.json"
    with pytest.raises(FileNotFoundError, match=rf"^{re.escape(str(missing))}: cannot read the config file"):
        read_config_file(missing)
    bad = tmp_path / "bad.json"
    bad.write_text('{"seed": 1,')
    with pytest.raises(ValueError, match=rf"^{re.escape(str(bad))}: not valid JSON \(Expecting"):
        read_config_file(bad)
    bad.write_bytes(b'{"note": "\xff"}')
    with pytest.raises(ValueError, match=r"not valid JSON \(not UTF-8 text"):
        read_config_file(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(CorruptFileError, match="not a JSON object"):
        read_config_file(bad)
    sealed = tmp_path / "train_config.json"
    write_checked_json(sealed, {"seed": 1})
    config = read_config_file(sealed)
    assert config.settings == {"seed": 1} and config.sealed
    sealed.write_text(sealed.read_text().replace('"seed": 1', '"seed": 2'))
    with pytest.raises(CorruptFileError, match="contents do not match its sha256"):
        read_config_file(sealed)


def test_the_scope_hands_on_the_reading_and_nothing_after_it(tmp_path):
    path = tmp_path / "c.json"
    path.write_text('{"seed": 1}')
    first = read_config_file(path)
    with config_scope(first):
        path.write_text('{"seed": 2}')
        assert config_file(str(path)) is first  # the command's reading, not a second one
        assert config_file(first) is first and config_file(None) is None
    assert config_file(path).settings == {"seed": 2}
    assert ConfigFile(path, {"train": {"seed": 1}, "record": {}}).run_settings == {"seed": 1}


def test_draccus_is_handed_the_settings_and_the_flags_override_them(tmp_path, opened):
    from sr_imitation.infra.cli_errors import split_config_path
    from sr_imitation.infra.cli_parsing import merged, parse_command
    from sr_imitation.substrates.sac.config import RLTrainConfig

    path = tmp_path / "c.json"
    path.write_text(json.dumps({"seed": 4, "sleep": {"lr": 0.5, "max_iterations": 7}}))
    assert split_config_path(["--config_path", str(path), "--seed=1"]) == (str(path), ["--seed=1"])
    cfg = parse_command(RLTrainConfig, ["--config_path", str(path), "--sleep.lr=0.25"], prog="x")
    assert (cfg.seed, cfg.sleep.lr, cfg.sleep.max_iterations) == (4, 0.25, 7)
    assert opened.count(path.resolve()) == 1
    assert merged({"a": {"b": 1, "c": 2}, "d": 3}, {"a": {"b": 5}, "e": 6}) == {"a": {"b": 5, "c": 2}, "d": 3, "e": 6}
