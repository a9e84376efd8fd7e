"""A method's options and the shared settings it replaces are checked before anything is written (issue 88 item 2):
a wrongly typed ``--method_options`` value is one line naming the option, its type and the value, and a flag of a
shared setting the method replaces with an option of its own (``--method=reset_distill --sleep.max_iterations=3``)
is one line naming the option to give instead, on every substrate; the option's value is the one used and
fingerprinted."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from sr_imitation.core.sleep import SleepConfig
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.stream import METHODS

SUBSTRATE_FLAGS = {
    "act": ["--substrate=act", "--stream.stats=first"],  # EWC keeps normalized data: not the default stats
    "sac": ["--substrate=sac"],
    "toy": ["--substrate=toy"],
}
"""Each substrate's flags for a run of EWC / Reset & Distill (the data are never read: the refusals come first)."""

REPLACING = sorted(name for name, cls in METHODS.items() if cls.own_settings or cls.fixed_settings)


def _one_line(sr_train, args, capsys) -> str:
    """``sr-train args``' one error line (exit 2, no traceback)."""
    with pytest.raises(SystemExit) as info:
        run_cli("sr-train", sr_train, args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("sr-train: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("substrate", sorted(SUBSTRATE_FLAGS))
def test_a_wrongly_typed_method_option_is_one_line_naming_it_before_any_run_folder(tmp_path, sr_train, capsys,
                                                                                  substrate):
    out = tmp_path / "run"
    args = [*SUBSTRATE_FLAGS[substrate], "--method=ewc", "--method_options={lam: abc}", f"--output_dir={out}"]
    line = _one_line(sr_train, args, capsys)
    assert line.startswith("sr-train: error: method_options: lam: expects a number, got 'abc'"), line
    assert not out.exists() and not any(tmp_path.iterdir())


def test_method_options_are_parsed_as_their_option_s_type_and_booleans_are_strict(tmp_path, sr_train, capsys):
    line = _one_line(sr_train, ["--substrate=toy", "--method=sr", "--method_options={reset_wake: 1}",
                                f"--output_dir={tmp_path / 'bad'}"], capsys)
    assert "method_options: reset_wake" in line and "1" in line and not (tmp_path / "bad").exists()
    out = tmp_path / "run"
    sr_train(["--substrate=toy", "--method=ewc", "--method_options={lam: 100}", "--stream.skills=[a,b]",
              "--progress=false", f"--output_dir={out}"])
    fingerprint = json.loads((out / "settings_fingerprint.json").read_text())
    assert repr(fingerprint["settings"]["method_config.lam"]) == "100.0"  # the number, as its option's float


@pytest.mark.parametrize("substrate", sorted(SUBSTRATE_FLAGS))
def test_a_budget_flag_the_method_replaces_is_refused_naming_its_option_on_every_substrate(tmp_path, sr_train,
                                                                                          capsys, substrate):
    out = tmp_path / "run"
    args = [*SUBSTRATE_FLAGS[substrate], "--method=reset_distill", "--sleep.max_iterations=3", f"--output_dir={out}"]
    line = _one_line(sr_train, args, capsys)
    assert line.startswith("sr-train: error: --sleep.max_iterations: reset_distill sets it with its own option "
                           "'iterations' (default 2000); use --method_options={iterations: 3}"), line
    assert not out.exists() and not any(tmp_path.iterdir())


@pytest.mark.parametrize("method", REPLACING)
def test_every_setting_a_method_replaces_is_refused_as_a_flag_whatever_its_form(tmp_path, sr_train, capsys, method):
    cls = METHODS[method]
    assert {"reset_distill", "progress_compress"} <= set(REPLACING)
    for setting, option in cls.own_settings.items():
        for form in ([f"--{setting}=7"], [f"--{setting}", "7"]):
            line = _one_line(sr_train, ["--substrate=toy", f"--method={method}", *form,
                                        f"--output_dir={tmp_path / 'run'}"], capsys)
            assert f"--{setting}: {method} sets it with its own option {option!r}" in line, line
            assert f"use --method_options={{{option}: 7}}" in line, line
    for setting, value in cls.fixed_settings.items():
        line = _one_line(sr_train, ["--substrate=toy", f"--method={method}", f"--{setting}=1",
                                    f"--output_dir={tmp_path / 'run'}"], capsys)
        assert f"--{setting}: {method} fixes it at {value!r}" in line, line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("method", REPLACING)
def test_the_declared_settings_are_the_ones_the_method_s_sleep_uses(method):
    """``own_settings`` / ``fixed_settings`` are not a second list beside the code: the sleep configuration the
    method builds is exactly the run's with them in place."""
    cls = METHODS[method]
    fields = {f.name for f in dataclasses.fields(SleepConfig)}
    declared = {k: v for k, v in {**cls.fixed_settings, **cls.own_settings}.items() if k != "sleep.enabled"}
    assert {key.split(".", 1)[1] for key in declared} <= fields and all(k.startswith("sleep.") for k in declared)
    if "sleep.enabled" in cls.fixed_settings:  # the run's switch, which the method's sleeps_after answers itself
        assert all(cls.sleeps_after(cls.__new__(cls), n) for n in (1, 2, 3))
    assert set(cls.own_settings.values()) <= {f.name for f in dataclasses.fields(cls.config)}
    run = SleepConfig(max_iterations=11, batch_size=5, lr=0.5, aggregator="nash", anchor_strength=2.0,
                      early_stop_tol=0.3, early_stop_window=9)
    method_ = cls.__new__(cls)
    method_.config = dataclasses.replace(cls.config, **dict.fromkeys(cls.own_settings.values(), 3))
    used = method_.own_sleep_config(run)
    for key, value in declared.items():
        field = key.split(".", 1)[1]
        expected = 3 if key in cls.own_settings else value
        assert getattr(used, field) == expected, key
    assert used.early_stop_window == 9  # a setting it does not declare stays the run's


def test_the_option_is_the_value_used_and_fingerprinted_and_a_config_file_s_setting_is_not_a_flag(
        tmp_path, sr_train, monkeypatch):
    """A config file's (a preset's, a run's own train_config.json) sleep settings are every method's; the method's
    option is used, fingerprinted, and the run resumes from its own file."""
    from sr_imitation.core.sleep import sleep_consolidate as real_sleep

    used = []

    def recording(params, policy, memories, config, **kwargs):
        used.append(config.max_iterations)
        return real_sleep(params, policy, memories, config, **kwargs)

    monkeypatch.setattr("sr_imitation.stream.substrate.sleep_consolidate", recording)
    preset = tmp_path / "preset.json"
    preset.write_text(json.dumps({"substrate": "toy", "sleep": {"max_iterations": 9}}))
    out = tmp_path / "run"
    sr_train([f"--config_path={preset}", "--method=reset_distill", "--method_options={iterations: 3}",
              "--stream.skills=[a,b]", "--progress=false", f"--output_dir={out}"])
    assert used == [3, 3]  # the distillation after each skill, with the method's own budget
    settings = json.loads((out / "settings_fingerprint.json").read_text())["settings"]
    assert settings["method_config.iterations"] == 3
    sr_train([f"--config_path={out / 'train_config.json'}", "--resume=true"])  # finished: nothing to redo
    assert used == [3, 3]


def test_a_whole_number_is_an_integer_option_s_integer_and_nothing_else_is():
    """``--method_options`` arrive as ``bool | float | str`` (``{iterations: 3}`` is 3.0): a whole number is the
    integer option's, a fraction is refused naming the option and its type."""
    from sr_imitation.stream.methods.registry import method_config

    assert method_config("reset_distill", {"iterations": 3.0})["iterations"] == 3
    assert type(method_config("reset_distill", {"iterations": 3.0})["iterations"]) is int
    assert type(method_config("ewc", {"lam": 100})["lam"]) is float
    with pytest.raises(ValueError, match=r"^method_options: iterations: expects an integer, got 3.5$"):
        method_config("reset_distill", {"iterations": 3.5})
    with pytest.raises(ValueError, match=r"^method_options: iterations: expects an integer, got true$"):
        method_config("reset_distill", {"iterations": True})


def test_sr_main_refuses_the_same_flags_under_its_train_section(tmp_path, capsys):
    """``sr-main`` (a preset's train section, flags ``--train.*``) follows the same rule, before recording or
    training anything."""
    from sr_imitation.main_job import main

    out = tmp_path / "run"
    preset = Path(__file__).resolve().parents[2] / "configs" / "needle_cpu.json"
    args = [f"--config_path={preset}", "--train.method=reset_distill", "--train.sleep.lr=0.001",
            f"--train.output_dir={out}", f"--record.root={tmp_path / 'datasets'}"]
    with pytest.raises(SystemExit):
        run_cli("sr-main", main, args)
    line = [x for x in capsys.readouterr().err.splitlines() if x.startswith("sr-main: error:")]
    assert line == ["sr-main: error: --train.sleep.lr: reset_distill sets it with its own option 'lr' (default "
                    "0.0003); use --train.method_options={lr: 0.001} (--debug shows the traceback)"], line
    assert not any(tmp_path.iterdir())


def test_a_file_written_for_the_method_that_sets_a_setting_it_replaces_is_refused_naming_the_file_and_option(
        tmp_path, sr_train, capsys):
    """The flags' rule for a config file a person wrote for the method (its ``method`` key): the key is refused in
    one line naming the file and the method option to set instead, before any folder is written. A preset that names
    another method (or none) is every method's and a run's own ``train_config.json`` holds every setting: both run
    (the test above)."""
    out = tmp_path / "run"
    mine = tmp_path / "mine.json"
    mine.write_text(json.dumps({"substrate": "toy", "method": "reset_distill", "sleep": {"max_iterations": 9}}))
    line = _one_line(sr_train, [f"--config_path={mine}", f"--output_dir={out}"], capsys)
    assert line.startswith(f"sr-train: error: {mine}: sleep.max_iterations: reset_distill sets it with its own "
                           "option 'iterations' (default 2000); set \"method_options\": {\"iterations\": 9} "
                           "instead"), line
    mine.write_text(json.dumps({"substrate": "toy", "method": "reset_distill", "sleep": {"anchor_strength": 1.0}}))
    line = _one_line(sr_train, [f"--config_path={mine}", "--method=reset_distill", f"--output_dir={out}"], capsys)
    assert line.startswith(f"sr-train: error: {mine}: sleep.anchor_strength: reset_distill fixes it at 0.0 "
                           "whatever the file says; leave it out"), line
    assert not out.exists()
    shared = tmp_path / "shared.json"  # written for SR: every method may run it, the method's option wins
    shared.write_text(json.dumps({"substrate": "toy", "method": "sr", "sleep": {"max_iterations": 9}}))
    from sr_imitation import cli

    assert cli.parse_args([f"--config_path={shared}", "--method=reset_distill"]).method == "reset_distill"


def test_sr_main_refuses_a_preset_written_for_the_method_that_sets_what_it_replaces(tmp_path, capsys):
    from sr_imitation.main_job import main

    preset = json.loads((Path(__file__).resolve().parents[2] / "configs" / "needle_cpu.json").read_text())
    preset["train"]["method"] = "reset_distill"
    path = tmp_path / "preset.json"
    path.write_text(json.dumps(preset))
    with pytest.raises(SystemExit):
        run_cli("sr-main", main, [f"--config_path={path}", f"--train.output_dir={tmp_path / 'run'}",
                                  f"--record.root={tmp_path / 'datasets'}"])
    line = [x for x in capsys.readouterr().err.splitlines() if x.startswith("sr-main: error:")]
    assert line == [f"sr-main: error: {path}: train.sleep.max_iterations: reset_distill sets it with its own option "
                    "'iterations' (default 2000); set \"train.method_options\": {\"iterations\": 1000} instead "
                    "(--debug shows the traceback)"], line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preset.json"]
