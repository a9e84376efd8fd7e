"""User errors on the command line are one line naming the key or file (exit status 2), found before anything is
written; ``--debug`` shows the traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import sr_imitation.substrates.act.cli as imitation_cli
import sr_imitation.substrates.sac.cli as rl_cli
from sr_imitation.infra.cli_errors import run_cli, split_debug
from sr_imitation.infra.fingerprint import SettingsMismatchError


def _one_line_error(prog, main, args, capsys) -> str:
    with pytest.raises(SystemExit) as info:
        run_cli(prog, main, args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(f"{prog}: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("flag, key", [
    ("--wake.budget_scale=nan", "wake.budget_scale"),
    ("--sleep.lr=inf", "sleep.lr"),
    ("--sac.actor_lr=nan", "actor_lr"),
    ("--eval.episodes=0", "episodes"),
    ("--method=lwf", "method"),  # an imitation baseline, not defined on SAC
])
def test_rl_bad_values_are_one_line_naming_the_key_and_nothing_is_written(tmp_path, capsys, flag, key):
    out = tmp_path / "run"
    line = _one_line_error("sr-rl-train", rl_cli.main,
                           ["--config_path=configs/sac_mt5_cpu.json", f"--output_dir={out}", flag], capsys)
    assert key in line, line
    assert not out.exists()


@pytest.mark.parametrize("flag, key", [
    ("--sleep.anchor_strength=nan", "anchor_strength"),
    ("--sleep.lr=inf", "lr"),
    ("--policy.distill_weight_later=nan", "distill_weight_later"),
    ("--wake.batch_size=0", "batch_size"),
    ("--method=der", "method"),  # an MT5 baseline, not defined on ACT
])
def test_imitation_bad_values_are_one_line_naming_the_key_and_nothing_is_written(tmp_path, capsys, flag, key):
    out = tmp_path / "run"
    line = _one_line_error("sr-train", imitation_cli.train_main, [f"--output_dir={out}", flag], capsys)
    assert key in line, line
    assert not out.exists()


def test_an_unknown_flag_value_is_argparse_s_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        run_cli("sr-train", imitation_cli.train_main, [f"--output_dir={tmp_path / 'run'}", "--policy.type=act"])
    assert info.value.code == 2
    assert "argument --policy.type: invalid choice: 'act' (choose from 'act_sr')" in capsys.readouterr().err


def test_a_missing_dataset_is_one_line_naming_it(tmp_path, capsys):
    out = tmp_path / "run"
    line = _one_line_error("sr-train", imitation_cli.train_main,
                           [f"--output_dir={out}", f"--stream.dataset_root={tmp_path / 'nowhere'}",
                            "--stream.skills=[approach]"], capsys)
    assert str(tmp_path / "nowhere" / "approach") in line and not out.exists()


def test_a_refused_resume_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "settings_fingerprint.json").write_text("{}")
    line = _one_line_error("sr-rl-train", rl_cli.main,
                           ["--config_path=configs/sac_mt5_cpu.json", f"--output_dir={out}", "--resume=true"], capsys)
    assert "settings_fingerprint.json" in line
    with pytest.raises(Exception) as info:
        run_cli("sr-rl-train", rl_cli.main, ["--config_path=configs/sac_mt5_cpu.json", f"--output_dir={out}",
                                             "--resume=true", "--debug"])
    assert "settings_fingerprint.json" in str(info.value)
    assert json.loads((out / "settings_fingerprint.json").read_text()) == {}  # nothing rewritten


def test_changed_settings_name_every_key(tmp_path, capsys):
    err = SettingsMismatchError(tmp_path / "f.json", {"a.b": (1, 2), "c": ("x", "y")})
    with pytest.raises(SystemExit):
        run_cli("sr-train", lambda args: (_ for _ in ()).throw(err), [])
    line = capsys.readouterr().err.strip()
    assert line.startswith("sr-train: error:") and 'a.b: 1 -> 2; c: "x" -> "y"' in line


def test_bugs_keep_their_traceback_and_debug_flag_is_parsed():
    with pytest.raises(KeyError):
        run_cli("sr-train", lambda args: {}["missing"], [])
    assert split_debug(["--x=1", "--debug"]) == (True, ["--x=1"])
    assert split_debug(["--debug=false"]) == (False, [])


@pytest.mark.parametrize("preset", ["configs/needle_cpu.json", "configs/needle_cpu_vision.json",
                                    "configs/needle_paper.json"])
def test_needle_presets_are_runnable_by_sr_train_and_sr_main(preset):
    """The module docstring's ``sr-train --config_path=configs/needle_cpu.json`` failed (DecodingError: fields
    record, train): a preset's train section is now what sr-train runs, with its record.root datasets."""
    from sr_imitation.main_job import MainJobConfig
    from sr_imitation.substrates.act.cli import parse_config

    main = parse_config(MainJobConfig, preset, [])
    train = imitation_cli.parse_train_config(preset, ["--seed=5"])
    assert train.seed == 5 and train.stream.dataset_root == main.record.root
    assert train.policy.dim_model == main.train.policy.dim_model and train.wake == main.train.wake


def test_a_dataset_root_flag_on_a_preset_is_never_silently_dropped(capsys, monkeypatch):
    """``sr-train --config_path=<sr-main preset> --stream.dataset_root=X`` read the preset's ``record.root`` and
    ignored X without a word; now the flag overrides it like any flag (both spellings). ``sr-main`` reads its datasets
    where it records them: a ``--train.stream.dataset_root`` elsewhere is one line naming both keys."""
    from sr_imitation.main_job import MainJobConfig
    from sr_imitation.substrates.act.cli import parse_config

    preset = "configs/needle_cpu_m16.json"
    assert imitation_cli.parse_train_config(preset, []).stream.dataset_root == Path("datasets/needle_cpu")
    for args in (["--stream.dataset_root=elsewhere"], ["--stream.dataset_root", "elsewhere"]):
        train = imitation_cli.parse_train_config(preset, ["--seed=3", *args])
        assert train.stream.dataset_root == Path("elsewhere") and train.seed == 3
    import sr_imitation.main_job as main_job_module

    monkeypatch.setattr(main_job_module, "ensure_recorded", lambda record: pytest.fail("recorded"))
    driven = main_job_module.preset_with_datasets(preset, ["--stream.dataset_root=elsewhere"])  # the drivers' start
    assert driven.train.stream.dataset_root == Path("elsewhere")
    main = parse_config(MainJobConfig, preset, ["--record.root=mine"])
    assert main.train.stream.dataset_root == main.record.root == Path("mine")
    assert parse_config(MainJobConfig, preset, ["--train.stream.dataset_root=datasets/needle_cpu"]).record.root \
        == Path("datasets/needle_cpu")
    from sr_imitation.main_job import main as main_job

    line = _one_line_error("sr-main", main_job, [f"--config_path={preset}", "--train.stream.dataset_root=elsewhere"],
                           capsys)
    assert line.startswith("sr-main: error: train.stream.dataset_root: 'elsewhere', but this job reads its datasets "
                           "where it records them (record.root: 'datasets/needle_cpu'); give the folder as "
                           "--record.root"), line


@pytest.mark.parametrize("skills, says", [
    ("[]", "stream.skills: the stream needs at least one skill"),
    ("[approach,place,approach]", "stream.skills must be distinct, got ['approach', 'place', 'approach'] "
                                  "(['approach'] more than once)"),
])
def test_a_stream_s_skill_list_errors_name_the_key(skills, says, tmp_path, capsys):
    from sr_imitation.cli import train_main

    line = _one_line_error("sr-train", train_main, [f"--stream.skills={skills}", f"--output_dir={tmp_path / 'o'}"],
                           capsys)
    assert line.startswith(f"sr-train: error: {says}"), line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, expected", [
    ('{"seed": 1,', r"sr-train: error: .*bad.json: not valid JSON \(Expecting"),  # names the file
    ('{"seed": "abc"}', r"sr-train: error: .*bad.json: seed: expects an integer, got 'abc' \("),  # the key, value
])
def test_a_malformed_config_file_names_the_file_or_the_key(tmp_path, capsys, text, expected):
    import re

    from sr_imitation.cli import train_main

    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(SystemExit):
        run_cli("sr-train", train_main, [f"--config_path={path}", f"--output_dir={tmp_path / 'out'}"])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.match(expected, err), err
    assert not (tmp_path / "out").exists()


def test_every_python_m_command_answers_user_errors_in_one_line():
    """Each module run as ``python -m`` (the README's experiment commands) goes through ``run_cli``, in its
    ``__main__`` block or in the function that block calls: ``needle_compare``, ``mt5_compare`` and ``sleep_replay``
    printed a draccus traceback for a bad ``--extra`` value. Benchmarks (developer tools) and modules another command
    calls (the Meta-World recorder, under ``sr-record``) are left out; ``recompute_bwt`` (the repository's
    ``experiments/``, beside the package's) answers through argparse, as does the grid's benchmark
    (``experiments/grid_benchmark.py``, a benchmark that lives beside the runner it times)."""
    import ast

    repo = Path(__file__).resolve().parents[1]
    exempt = {"sr_imitation/recorders/metaworld.py", "experiments/recompute_bwt.py",
              "sr_imitation/experiments/grid_benchmark.py"}
    unwired = []
    for path in sorted([*(repo / "sr_imitation").rglob("*.py"), *(repo / "experiments").rglob("*.py")]):
        rel = path.relative_to(repo).as_posix()
        if rel.startswith("sr_imitation/benchmarks/") or rel in exempt:
            continue
        tree = ast.parse(path.read_text())
        blocks = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
        if not blocks:
            continue
        functions = {node.name: ast.unparse(node) for node in tree.body if isinstance(node, ast.FunctionDef)}
        called = [n.func.id for n in ast.walk(blocks[0]) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
        if "run_cli" not in called and not any("run_cli(" in functions.get(name, "") for name in called):
            unwired.append(rel)
    assert unwired == []


def test_every_command_parses_through_parse_command():
    """A command's flags are parsed by :func:`~sr_imitation.infra.cli_parsing.parse_command` (an unknown flag is one
    line naming the nearest, a text flag holds what was typed), never by ``draccus.parse`` directly: ``sr-grid`` and the
    experiment modules printed argparse's whole usage block for a mistyped flag. The one exception is the benchmark
    that times draccus itself."""
    import ast

    root = Path(__file__).resolve().parents[1] / "sr_imitation"
    exempt = {"infra/cli_parsing.py", "benchmarks/cli_parse.py"}
    direct = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if (rel not in exempt and isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "parse" and ast.unparse(node.func.value) == "draccus"):
                direct.append(f"{rel}:{node.lineno}")
    assert direct == []


@pytest.mark.parametrize("module", [
    "sr_imitation.experiments.needle_compare", "sr_imitation.experiments.mt5_compare", "sr_imitation.experiments.grid",
    "sr_imitation.experiments.sleep_replay", "sr_imitation.experiments.hypotheses",
    "sr_imitation.experiments.main_compare", "experiments.calibration", "experiments.memory_budget",
    "experiments.skill_probe", "sr_imitation.benchmarks.needle_expert", "sr_imitation.benchmarks.demo_endings",
    "sr_imitation.benchmarks.needle_env", "sr_imitation.envs.needle.chained",
])
def test_a_mistyped_flag_of_an_experiment_command_is_one_line_naming_the_command(module, capsys):
    """Run in-process as its ``__main__`` block runs it: ``--seedz`` is refused before anything is read or written,
    in one line that names the command as a user types it (``python -m ...``; the grid's console script
    ``sr-grid``)."""
    import importlib

    mod = importlib.import_module(module)
    prog = "sr-grid" if module == "sr_imitation.experiments.grid" else f"python -m {module}"
    assert getattr(mod, "PROG", "sr-grid") == prog
    with pytest.raises(SystemExit) as exc:
        run_cli(prog, mod.main, ["--seedz=1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"{prog}: error: unknown flag --seedz"), err
    assert "usage:" not in err
