"""Every value is the type it claims (:mod:`sr_imitation.infra.value_types`), over every field of every command's
config dataclass: each numeric field given ``true``, ``null`` (unless it may be null) or a text, each boolean field
given a number, on the command line and in a config file, is refused in one line naming the key and the value; and no
value the project itself writes (the presets, every archived run's ``train_config.json``) is refused.

Before: ``--sleep.lr=true`` ran with lr 1.0, ``"max_epochs": true`` trained one epoch (both rc 0), and ``null`` for a
number was an internal "decode_int() missing 1 required positional argument"."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import draccus
import pytest

from sr_imitation.infra.cli_errors import UsageError
from sr_imitation.infra.cli_parsing import check_flag_types
from sr_imitation.infra.value_types import check_settings, value_problems
from sr_imitation.io import read_config_json

REPO = Path(__file__).resolve().parents[2]


def command_configs() -> dict[str, type]:
    """The config dataclass of every ``sr-*`` command that parses one."""
    from sr_imitation.experiments.grid import GridConfig
    from sr_imitation.experiments.main_compare import MainCompareConfig
    from sr_imitation.recorders.metaworld import MetaWorldRecordConfig
    from sr_imitation.recorders.needle import RecordConfig
    from sr_imitation.substrates.act.cli import EvalCommandConfig
    from sr_imitation.substrates.act.config import MainJobConfig, TrainStreamConfig
    from sr_imitation.substrates.act.offline_sleep import OfflineSleepConfig
    from sr_imitation.substrates.sac.config import RLTrainConfig
    from sr_imitation.substrates.sac.resleep import ResleepConfig

    return {"sr-train": TrainStreamConfig, "sr-train --substrate=sac": RLTrainConfig, "sr-main": MainJobConfig,
            "sr-eval": EvalCommandConfig, "sr-sleep": OfflineSleepConfig, "sr-record": RecordConfig,
            "sr-record --env=metaworld": MetaWorldRecordConfig, "sr-grid": GridConfig, "sr-sac-sleep": ResleepConfig,
            "main_compare (.ci/main.sh)": MainCompareConfig}


@pytest.fixture(autouse=True)
def _act_sr_only():
    """``--policy`` knows act_sr only, as while sr-train parses (:func:`act_sr_choices_only`)."""
    from sr_imitation.substrates.act.cli import act_sr_choices_only

    with act_sr_choices_only():
        yield


def _union(tp: Any) -> tuple[list[Any], bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        return [a for a in args if a is not type(None)], type(None) in args
    return [tp], False


def _sections(tp: Any) -> list[tuple[type, str | None]]:
    """The dataclasses a field holds, each with the ``type`` key that selects it (draccus choice types)."""
    out = []
    for member in _union(tp)[0]:
        if isinstance(member, type) and issubclass(member, draccus.ChoiceRegistry):
            out += [(cls, name) for name, cls in member.get_known_choices().items()]
        elif isinstance(member, type) and dataclasses.is_dataclass(member):
            out.append((member, None))
    return out


def leaves(cls: type, path: tuple = ()) -> Iterator[tuple[tuple, str, Any, Any]]:
    """Every non-section field below ``cls``: (its path of (section, choice type) pairs, its name, its type, its
    default)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        sections = _sections(hints[f.name])
        if sections:
            for klass, choice in sections:
                yield from leaves(klass, (*path, (f.name, choice)))
        else:
            yield path, f.name, hints[f.name], f.default


def kind(tp: Any) -> str | None:
    members, _ = _union(tp)
    if set(members) <= {int, float} and members:
        return "number"
    return "bool" if members == [bool] else None


def typed_fields() -> list[tuple[str, tuple, str, Any, Any]]:
    """(command, path, name, type, default) of every numeric or boolean field of every command's config."""
    out = []
    for command, cls in command_configs().items():
        for path, name, tp, default in leaves(cls):
            if kind(tp) is not None:
                out.append((command, path, name, tp, default))
    return out


def wrong_values(tp: Any, default: Any) -> list[tuple[Any, str]]:
    """The wrong values a field of type ``tp`` is given: (the value, its text on the command line); a value of the
    default's own type is left out (a default that contradicts its annotation says what the field holds)."""
    _, optional = _union(tp)
    if kind(tp) == "number":
        values = [(True, "true"), (False, "false"), (None, "null"), ("abc", "abc"), ("", "")]
        if optional:
            values = [v for v in values if v[0] is not None]
    else:
        values = [(1, "1"), (0, "0"), (2.5, "2.5"), (None, "null"), ("maybe", "maybe")]
        if optional:
            values = [v for v in values if v[0] is not None]
    return [(v, t) for v, t in values if default is dataclasses.MISSING or type(v) is not type(default)]


def nested(path: tuple, name: str, value: Any) -> dict[str, Any]:
    """A config file's data setting only ``name`` below ``path`` to ``value``."""
    data: dict[str, Any] = {name: value}
    for section, choice in reversed(path):
        data = {**({"type": choice} if choice else {}), **data}
        data = {section: data}
    return data


def shown(value: Any) -> str:
    """A value as the messages name it."""
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    return repr(value) if isinstance(value, str) else str(value)


def test_the_walk_reaches_the_fields_the_issue_names():
    keys = {(c, ".".join([*(s for s, _ in p), n])) for c, p, n, _, _ in typed_fields()}
    for key in [("sr-train", "sleep.lr"), ("sr-train", "wake.max_epochs"), ("sr-train", "policy.dim_model"),
                ("sr-train", "progress"), ("sr-train --substrate=sac", "sleep.lr"), ("sr-main", "train.seed"),
                ("sr-eval", "eval.episodes"), ("sr-sleep", "sleep.lr"), ("sr-record", "num_episodes"),
                ("sr-grid", "ray.num_cpus")]:
        assert key in keys, key
    assert len(keys) > 150


def test_every_numeric_and_boolean_field_refuses_a_value_of_another_type_in_a_config_file():
    checked = 0
    for command, path, name, tp, default in typed_fields():
        key = ".".join([*(s for s, _ in path), name])
        for value, _ in wrong_values(tp, default):
            cls = command_configs()[command]
            with pytest.raises(ValueError) as refused:
                check_settings(cls, nested(path, name, value), "my.json")
            message = str(refused.value)
            assert "\n" not in message, (command, key, value)
            assert message.startswith(f"my.json: {key}: expects "), (command, key, message)
            assert message.endswith(f"got {shown(value)}"), (command, key, message)
            checked += 1
    assert checked > 600


def test_every_numeric_and_boolean_field_refuses_a_value_of_another_type_on_the_command_line():
    checked = 0
    for command, path, name, tp, default in typed_fields():
        key = ".".join([*(s for s, _ in path), name])
        for value, text in wrong_values(tp, default):
            with pytest.raises(UsageError) as refused:
                check_flag_types(command_configs()[command], [f"--{key}={text}"])
            message = str(refused.value)
            assert "\n" not in message, (command, key, text)
            assert message.startswith(f"{key}: expects "), (command, key, message)
            assert message.endswith(f"got {shown(value)} (--{key}={text})"), (command, key, message)
            checked += 1
    assert checked > 600


def test_the_right_types_pass_numbers_as_text_included():
    from sr_imitation.substrates.act.config import TrainStreamConfig

    good = ["--sleep.lr=1e-4", "--sleep.lr=0.5", "--sleep.lr=2", "--wake.max_epochs=3", "--progress=false",
            "--policy.optimizer_lr=1e-5", "--seed", "7", "--eval.seeds=[0,1,2]"]
    check_flag_types(TrainStreamConfig, good)
    check_settings(TrainStreamConfig, {"sleep": {"lr": "1e-4", "early_stop_tol": 0}, "wake": {"max_epochs": 3},
                                       "progress": True, "seed": 0}, "my.json")
    with pytest.raises(UsageError, match=r"^eval.seeds: \[1\] expects an integer, got true \(--eval.seeds=\[0,tr"):
        check_flag_types(TrainStreamConfig, ["--eval.seeds=[0,true]"])
    with pytest.raises(ValueError, match=r"^my.json: wake.max_epochs: expects an integer, got 2.5$"):
        check_settings(TrainStreamConfig, {"wake": {"max_epochs": 2.5}}, "my.json")


def _tracked(pattern: str) -> list[Path]:
    out = subprocess.run(["git", "ls-files", pattern], cwd=REPO, capture_output=True, text=True, check=True).stdout
    return [REPO / line for line in out.split()]


def test_no_value_the_project_writes_is_refused():
    """The presets and every archived run's train_config.json (what a resume reads back): no false refusals, e.g.
    LeRobot's ``replace_final_stride_with_dilation: int = False`` holds a boolean in every ACT run."""
    from sr_imitation.substrates.act.config import MainJobConfig, TrainStreamConfig
    from sr_imitation.substrates.sac.config import RLTrainConfig

    files = [*_tracked("configs/*.json"), *_tracked("docs/results/*train_config.json")]
    assert len(files) > 100
    for path in files:
        data, _ = read_config_json(path)
        sac = data.get("substrate") == "sac" or data.get("train", {}).get("substrate") == "sac"
        cls = MainJobConfig if "record" in data else RLTrainConfig if sac else TrainStreamConfig
        assert value_problems(cls, data) == [], path


def test_method_options_are_the_type_of_the_option():
    from sr_imitation.stream.methods.registry import method_config

    assert method_config("ewc", {"lam": 10.0}) == {**method_config("ewc"), "lam": 10.0}
    for value, says in [("abc", "'abc'"), (True, "true"), (None, "null")]:
        with pytest.raises(ValueError, match=rf"^method_options: lam: expects a number, got {says}$"):
            method_config("ewc", {"lam": value})
    with pytest.raises(ValueError, match=r"got '1e-3' \(read as text: write it with a decimal point"):
        method_config("ewc", {"lam": "1e-3"})  # nothing would turn the text into a number


def test_null_is_accepted_where_the_field_may_be_null():
    from sr_imitation.substrates.act.config import TrainStreamConfig

    optional = [(p, n) for c, p, n, tp, d in typed_fields() if c == "sr-train" and (_union(tp)[1] or d is None)]
    assert optional
    for path, name in optional:
        assert value_problems(TrainStreamConfig, nested(path, name, None)) == []


def test_a_config_file_s_bad_value_through_sr_train_writes_nothing(tmp_path, capsys):
    from sr_imitation import cli
    from sr_imitation.infra.cli_errors import run_cli

    preset = json.loads((REPO / "configs" / "needle_cpu.json").read_text())
    for where, value, says in [("max_epochs", True, "true"), ("max_epochs", None, "null")]:
        preset["train"].setdefault("wake", {})[where] = value
        path = tmp_path / "preset.json"
        path.write_text(json.dumps(preset))
        with pytest.raises(SystemExit) as exc:
            run_cli("sr-train", cli.train_main, [f"--config_path={path}", f"--output_dir={tmp_path / 'out'}"])
        assert exc.value.code == 2
        err = capsys.readouterr().err.splitlines()
        assert err == [f"sr-train: error: {path}: train.wake.max_epochs: expects an integer, got {says} "
                       "(--debug shows the traceback)"]
    with pytest.raises(SystemExit):
        run_cli("sr-train", cli.train_main, [f"--config_path={REPO / 'configs' / 'needle_cpu.json'}",
                                             "--sleep.lr=true", f"--output_dir={tmp_path / 'out'}"])
    assert capsys.readouterr().err.splitlines() == [
        "sr-train: error: sleep.lr: expects a number, got true (--sleep.lr=true) (sr-train --help lists every flag)"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preset.json"]  # nothing written, no lock left


@pytest.mark.parametrize("prog, module, flags", [
    ("sr-eval", "sr_imitation.substrates.act.cli:eval_main", ["--eval.episodes=true", "--policy.path={tmp}/m"]),
    ("sr-sleep", "sr_imitation.substrates.act.cli:sleep_main", ["--sleep.lr=true", "--policy.path={tmp}/m"]),
    ("sr-record", "sr_imitation.recorders.cli:main", ["--num_episodes=null", "--root={tmp}/d"]),
    ("sr-grid", "sr_imitation.experiments.grid:main", ["--ray.num_cpus=true", "--output_root={tmp}/g"]),
    ("sr-train", "sr_imitation.cli:train_main", ["--substrate=sac", "--seed=true"]),
])
def test_each_command_refuses_a_flag_of_another_type_in_one_line_writing_nothing(tmp_path, capsys, prog, module,
                                                                                  flags):
    import importlib

    from sr_imitation.infra.cli_errors import run_cli

    name, function = module.split(":")
    main = getattr(importlib.import_module(name), function)
    args = [f.replace("{tmp}", str(tmp_path)) for f in flags] + [f"--output_dir={tmp_path / 'out'}"] * (
        prog in ("sr-eval", "sr-sleep", "sr-train"))
    with pytest.raises(SystemExit) as exc:
        run_cli(prog, main, args)
    assert exc.value.code == 2
    err = capsys.readouterr().err.splitlines()
    key, text = args[1 if prog == "sr-train" else 0][2:].split("=")
    assert len(err) == 1 and err[0].startswith(f"{prog}: error: {key}: expects "), err
    assert f"(--{key}={text})" in err[0]
    assert list(tmp_path.iterdir()) == []
