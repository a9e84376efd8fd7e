"""A command line that teaches: every flag of every command has a meaning in ``--help``,
``--help`` works next to ``--config_path``, a typo is one line naming the nearest flag, LeRobot's names are mapped
or answered in one line, usage errors are one line with a pointer to ``--help``; the short ``needle_try``
preset."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from draccus.wrappers import docstring

import sr_imitation.infra.cli_parsing as cli_parsing
from lerobot_policy_act_sr import ACTSRConfig
from sr_imitation import cli, main_job
from sr_imitation.infra.cli_errors import run_cli
from sr_imitation.recorders import cli as record_cli
from sr_imitation.recorders import needle
from sr_imitation.stream.config import LEROBOT_EVAL_FLAGS, LEROBOT_TRAIN_FLAGS, RENAMED_FLAGS
from sr_imitation.substrates.act import cli as imitation_cli
from tests.test_cli_errors import _one_line_error

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
NEEDLE = str(CONFIGS / "needle_cpu.json")
TRY = CONFIGS / "needle_try.json"

COMMANDS = {  # the console entries' main functions, as run_cli runs them
    "sr-train": (cli.train_main, []),
    "sr-train --substrate=sac": (cli.train_main, ["--substrate=sac"]),
    "sr-train --config_path=<sr-main preset>": (cli.train_main, [f"--config_path={NEEDLE}"]),
    "sr-record": (needle.main, []),
    "sr-record --env=metaworld": (record_cli.main, ["--env=metaworld"]),
    "sr-eval": (imitation_cli.eval_main, []),
    "sr-sleep": (imitation_cli.sleep_main, []),
    "sr-main": (main_job.main, []),
}

FLAGS_WITHOUT_HELP_ALLOWED: dict[str, set[str]] = {command: set() for command in COMMANDS}
"""Flags allowed to show no meaning in ``--help``: none. A new field without a docstring fails here; give it one
(under the field, or an ``Args:`` entry of its class) or, for a field of a class this project cannot edit, an
entry of :data:`sr_imitation.infra.cli_parsing.INHERITED_FIELD_HELP`."""


def _help(command: str, monkeypatch, capsys) -> tuple[object, str]:
    """Run ``<command> --help`` through its console entry; returns the parser it built and the printed help."""
    built = []
    original = cli_parsing.command_parser

    def spy(*args, **kwargs):
        built.append(original(*args, **kwargs))
        return built[-1]

    monkeypatch.setattr(cli_parsing, "command_parser", spy)
    main, args = COMMANDS[command]
    prog = command.split()[0]
    with pytest.raises(SystemExit) as info:
        run_cli(prog, main, [*args, "--help"])
    assert info.value.code == 0
    return built[-1], capsys.readouterr().out


def _flags_without_help(parser) -> list[str]:
    return [a.option_strings[0] for a in parser.parser._actions
            if a.option_strings and a.option_strings[0].startswith("--") and a.option_strings[0] != "--help"
            and not (a.help or "").strip()]


# --- a meaning for every flag ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_flag_of_every_command_has_a_meaning_in_help(command, monkeypatch, capsys):
    """Before: sr-train 33 of 113 flags without a meaning, sr-train --substrate=sac 44 of 100, sr-record 16 of 17,
    sr-eval 5 of 20, sr-main 50 of 132 (counted the same way, on the parser each command builds)."""
    parser, out = _help(command, monkeypatch, capsys)
    flags = [s for a in parser.parser._actions for s in a.option_strings if s.startswith("--")]
    assert len(flags) > 10
    assert set(_flags_without_help(parser)) <= FLAGS_WITHOUT_HELP_ALLOWED[command]
    assert "usage: " + command.split()[0] in out


@pytest.mark.parametrize("command, flag, meaning", [
    ("sr-train", "--policy.distill_weight_later", "gamma_k, the wake distillation weight"),
    ("sr-train", "--policy.use_images", "state-only mode"),
    ("sr-train", "--policy.backbone_norm", "GroupNorm"),
    ("sr-train", "--policy.dim_model", "main hidden dimension"),  # LeRobot's ACTConfig Args list
    ("sr-train", "--policy.repo_id", "push_to_hub=true pushes"),  # INHERITED_FIELD_HELP
    ("sr-train", "--wandb.mode", "nothing leaves the machine"),  # a docstring with one colon
    ("sr-train --substrate=sac", "--excitability.wake_enabled", "Wake-exc off"),
    ("sr-train --substrate=sac", "--wake.default_budget.patience", "rolling mean reward"),
    ("sr-record", "--num_episodes", "Successful episodes per skill"),
    ("sr-eval", "--policy.path", "pretrained_model directory"),
    ("sr-main", "--expert_video", "full-suture video"),
])
def test_help_shows_the_meaning_under_the_flag(command, flag, meaning, monkeypatch, capsys):
    _, out = _help(command, monkeypatch, capsys)
    text = " ".join(out.split())
    at = text.index(f" {flag} ")
    assert meaning in text[at:at + 400], text[at:at + 400]


def test_the_act_sr_policy_s_own_fields_have_help_in_stock_lerobot_train():
    """Stock lerobot-train reads help with draccus alone: the plugin's own fields have docstrings it finds (no
    class ``Args:`` list shadowing them, no single colon in a first line)."""
    own = [name for name in ACTSRConfig.__annotations__ if not name.startswith("_")]
    assert {"distill_weight_second", "distill_reduction", "use_images", "backbone_norm", "sleep"} <= set(own)
    for name in own:
        text = docstring.get_preferred_help_text(docstring.get_attribute_docstring(ACTSRConfig, name))
        assert text and text.strip(), name


# --- --help next to --config_path -------------------------------------------------------------------------------------

@pytest.mark.parametrize("command, args, shows", [
    ("sr-train", [f"--config_path={NEEDLE}", "--help"], "--sleep.anchor_strength"),
    ("sr-train", [f"--config_path={CONFIGS / 'sac_mt5_cpu.json'}", "--help"], "--sac.actor_lr"),
    ("sr-train", [f"--config_path={TRY}", "--seed=3", "--help"], "--wake.max_epochs"),
    ("sr-main", [f"--config_path={NEEDLE}", "--help"], "--train.sleep.anchor_strength"),
])
def test_help_works_with_a_config_file(command, args, shows, capsys):
    """Before: ``sr-train --config_path=configs/needle_cpu.json --help`` exited 2 ("unrecognized arguments:
    --train.help"), the preset's flags being prefixed with ``--train.``."""
    main = {"sr-train": cli.train_main, "sr-main": main_job.main}[command]
    with pytest.raises(SystemExit) as info:
        run_cli(command, main, args)
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert shows in out
    if command == "sr-train":
        assert "--train." not in out  # sr-train's flags address the preset's train section without the prefix


def _help_default(out: str, flag: str) -> str:
    """The ``(default: ...)`` a ``--help`` text shows for ``flag`` (its help may wrap over several lines)."""
    block = re.search(rf"^  {re.escape(flag)} .*?\(default: ([^)]*)\)", out, re.S | re.M)
    assert block, flag
    return block.group(1)


@pytest.mark.parametrize("command, config, flag, key", [
    ("sr-train", "needle_cpu_m16.json", "--memory.buffer_size", ("train", "memory", "buffer_size")),
    ("sr-train", "needle_cpu_m16.json", "--stream.stats", ("train", "stream", "stats")),
    ("sr-main", "needle_cpu_m16.json", "--train.memory.buffer_size", ("train", "memory", "buffer_size")),
    ("sr-train", "sac_mt5_cpu.json", "--sac.batch_size", ("sac", "batch_size")),
])
def test_help_with_a_config_file_shows_its_values(command, config, flag, key, capsys):
    """``--help`` beside ``--config_path`` shows the file's values as the defaults, not the code's (before: the
    m16 preset's help said ``--memory.buffer_size ... (default: 1024)``, the preset holds 16)."""
    data = json.loads((CONFIGS / config).read_text())
    for part in key:
        data = data[part]
    main = {"sr-train": cli.train_main, "sr-main": main_job.main}[command]
    with pytest.raises(SystemExit) as info:
        run_cli(command, main, [f"--config_path={CONFIGS / config}", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert _help_default(out, flag) == str(data)
    assert "Defaults shown are the values of" in out and config in out


def test_help_without_a_config_file_shows_the_code_s_defaults(capsys):
    with pytest.raises(SystemExit):
        run_cli("sr-train", cli.train_main, ["--help"])
    out = capsys.readouterr().out
    assert _help_default(out, "--memory.buffer_size") == "1024" and "Defaults shown are the values" not in out


# --- a typo: one line with the nearest flag -------------------------------------------------------------------------

@pytest.mark.parametrize("prog, main, args, nearest", [
    ("sr-train", cli.train_main, ["--sleep.anchor_strenght=0.1"], "did you mean --sleep.anchor_strength?"),
    ("sr-train", cli.train_main, [f"--config_path={NEEDLE}", "--sleep.anchor_strenght=0.1"],
     "did you mean --sleep.anchor_strength?"),  # the preset's train section: named as given, no --train.
    ("sr-train", cli.train_main, ["--anchor_strength=0.1"], "did you mean --sleep.anchor_strength?"),
    ("sr-train", cli.train_main, ["--wake.batch=4"], "did you mean --wake.batch_size?"),  # no abbreviations
    ("sr-train", cli.train_main, ["--substrate=sac", "--batch_size=4"],
     "did you mean --sac.batch_size or --sleep.batch_size?"),
    ("sr-train", cli.train_main, ["--output-dir=x"], "did you mean --output_dir?"),
    ("sr-record", needle.main, ["--num_episode=3"], "did you mean --num_episodes?"),
    ("sr-eval", imitation_cli.eval_main, ["--policy.pth=x"], "did you mean --policy.path?"),
    ("sr-sleep", imitation_cli.sleep_main, ["--memorys=[a]"], "did you mean --memories?"),
    ("sr-main", main_job.main, [f"--config_path={NEEDLE}", "--train.seeed=1"], "did you mean --train.seed?"),
    ("sr-main", main_job.main, [f"--config_path={NEEDLE}", "--seed=1"],
     "did you mean --train.seed, --record.seed or --train.sleep.seed?"),
])
def test_a_typo_is_one_line_naming_the_nearest_flag(prog, main, args, nearest, tmp_path, capsys):
    out = tmp_path / "run"
    flag = "--output_dir" if prog in ("sr-train", "sr-eval", "sr-sleep") else "--root"
    flag = "--train.output_dir" if prog == "sr-main" else flag
    line = _one_line_error(prog, main, [*args, f"{flag}={out}"], capsys)
    assert "unknown flag" in line and line.endswith(f"{nearest} ({prog} --help lists every flag)"), line
    assert "usage:" not in line and not out.exists()


@pytest.mark.parametrize("args, says", [
    (["--sleep.lr"], "argument --sleep.lr: expected one argument"),
    (["stray"], "unrecognized arguments: stray"),
    (["--eval.env=maybe", "--eval.env"], "expected one argument"),
])
def test_other_usage_errors_are_one_line_with_a_pointer_to_help(args, says, tmp_path, capsys):
    line = _one_line_error("sr-train", cli.train_main, [f"--output_dir={tmp_path / 'run'}", *args], capsys)
    assert says in line and line.endswith("(sr-train --help lists every flag)"), line


def test_a_typo_from_the_shell_is_one_line_on_stderr():
    """The console entry as a process: exit status 2 and one line on stderr, not argparse's 56-line usage dump."""
    done = subprocess.run([sys.executable, "-m", "sr_imitation.cli", "--sleep.anchor_strenght=0.1"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == ["sr-train: error: unknown flag --sleep.anchor_strenght; did you mean "
                                        "--sleep.anchor_strength? (sr-train --help lists every flag)"], done.stderr


def test_help_with_a_preset_from_the_shell():
    done = subprocess.run([sys.executable, "-m", "sr_imitation.cli", "--config_path=configs/needle_cpu.json",
                           "--help"], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert "usage: sr-train" in done.stdout and "--train.help" not in done.stdout + done.stderr


# --- LeRobot's names ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("args, key, value", [
    (["--batch_size=4"], "batch_size", 4),
    (["--batch_size", "4"], "batch_size", 4),
    (["--num_workers=1"], "num_workers", 1),
    (["--dataset.video_backend=pyav"], "video_backend", "pyav"),
    ([f"--config_path={NEEDLE}", "--batch_size=4"], "batch_size", 4),
])
def test_lerobot_names_that_map_are_accepted(args, key, value):
    cfg = cli.parse_args(args)
    section = cfg.stream if key == "video_backend" else cfg.wake
    assert getattr(section, key) == value


@pytest.mark.parametrize("args, says", [
    (["--steps=100"], ["sr-train has no --steps", "--wake.max_epochs", "--sleep.max_iterations"]),
    (["--dataset.repo_id=me/pick"], ["sr-train has no --dataset.repo_id", "--stream.repo_ids=[me/pick,"]),
    (["--dataset.root=data/pick"], ["--stream.dataset_paths=[data/pick,"]),
    (["--env.type=pusht"], ["--eval.env=lerobot --eval.env_type=pusht"]),
    (["--policy.path=outputs/x/pretrained_model"],
     ["--resume=true", "sr-eval --policy.path=outputs/x/pretrained_model"]),
    (["--eval_freq=1000"], ["after every wake and every sleep"]),
    (["--policy.type=diffusion"], ["invalid choice: 'diffusion' (choose from 'act_sr')", "ACT-SR", "lerobot-train"]),
    (["--batch_size=4", "--wake.batch_size=8"], ["--batch_size is --wake.batch_size", "give one of them"]),
    ([f"--config_path={NEEDLE}", "--policy.type=diffusion"], ["invalid choice: 'diffusion'", "lerobot-train"]),
    (["--eval.n_episodes=10"], [RENAMED_FLAGS["--eval.n_episodes"]]),
])
def test_lerobot_names_without_a_match_are_answered_in_one_line(args, says, tmp_path, capsys):
    out = tmp_path / "run"
    line = _one_line_error("sr-train", cli.train_main, [*args, f"--output_dir={out}"], capsys)
    assert all(s in line for s in says), line
    assert not out.exists()


def test_sr_eval_takes_lerobot_eval_s_names(tmp_path, capsys):
    # mapped: --policy.device is sr-eval's --device (the run gets past parsing to the missing checkpoint)
    line = _one_line_error("sr-eval", imitation_cli.eval_main,
                           ["--policy.device=cpu", f"--policy.path={tmp_path / 'none'}"], capsys)
    assert "not a LeRobot pretrained_model directory" in line
    line = _one_line_error("sr-eval", imitation_cli.eval_main, ["--eval.n_episodes=10"], capsys)
    assert "sr-eval has no --eval.n_episodes" in line and "--eval.episodes=10 --eval.seeds=[0]" in line


def _flags_of(command: str) -> set[str]:
    cls = {"sr-train": imitation_cli.TrainStreamConfig, "sr-eval": imitation_cli.EvalCommandConfig}[command]
    with imitation_cli.act_sr_choices_only():
        return set(cli_parsing.option_names(cli_parsing.command_parser(cls, prog=command)))


@pytest.mark.parametrize("command, table", [("sr-train", LEROBOT_TRAIN_FLAGS), ("sr-eval", LEROBOT_EVAL_FLAGS)])
def test_the_lerobot_tables_name_real_flags(command, table):
    """Each mapped flag is a flag of the command, and every flag an answer proposes exists (a renamed setting would
    otherwise leave a stale answer)."""
    flags = _flags_of(command)
    for name, target in table.items():
        proposed = set(re.findall(r"(?<![\w-])--[a-z_][\w.]*", target)) - {"--policy.path"}  # sr-eval's, sr-sleep's
        assert proposed <= flags, (name, proposed - flags)
        if " " not in target:
            assert target in flags, name


# --- the first-look preset ------------------------------------------------------------------------------------------

def test_the_try_preset_parses_for_sr_main_and_sr_train_and_is_small():
    """configs/needle_try.json: the README's first look (a few minutes on 2 CPU cores; a full run is too long for
    the test suite - README and configs/README.md give the measured time)."""
    from sr_imitation.main_job import MainJobConfig

    cfg = imitation_cli.parse_config(MainJobConfig, TRY, [], prog="sr-main")
    train = cli.parse_args([f"--config_path={TRY}"])
    assert train.stream.skills == cfg.train.stream.skills == ["approach", "place", "insert"]
    assert train.stream.dataset_root == cfg.record.root == Path("datasets/needle_try")
    assert cfg.record.num_episodes <= 20 and len(cfg.train.eval.seeds) == 1 and cfg.train.eval.episodes <= 5
    assert cfg.train.wake.max_epochs * cfg.train.wake.max_steps_per_epoch <= 1200
    assert cfg.train.sleep.enabled and cfg.train.sleep.max_iterations <= 200
    assert Path(cfg.train.output_dir) == Path("outputs/needle_try")
    other_roots = {json.loads(p.read_text()).get("record", {}).get("root") for p in CONFIGS.glob("*.json") if p != TRY}
    assert str(cfg.record.root) not in other_roots  # its own datasets: other record settings are refused, not reused
    assert "needle_try.json" in (CONFIGS / "README.md").read_text()
    readme = (ROOT / "README.md").read_text()
    assert "sr-main --config_path=configs/needle_try.json" in readme and "first look" in readme



def test_draccus_reads_each_field_s_help_from_the_source_once_and_the_help_is_unchanged(monkeypatch, capsys):
    """draccus re-reads a class's whole source for every field at every parse (1.4 s of a 1.5 s sr-train parse);
    cli_parsing memoizes that lookup a process. The memo gives every draccus call site draccus' own record (equal,
    and a copy each time), a second parse asks draccus for none, and ``--help`` prints the same text with the memo
    as with draccus' original lookup."""
    assert docstring.get_attribute_docstring is cli_parsing._memoized_attribute_docstring
    original = cli_parsing._DRACCUS_ATTRIBUTE_DOCSTRING
    for name in ("sleep", "sleep_memory_size", "chunk_size"):
        first = docstring.get_attribute_docstring(ACTSRConfig, name)
        again = docstring.get_attribute_docstring(ACTSRConfig, name)
        assert first == again == original(ACTSRConfig, name) and first is not again
    asked = []
    monkeypatch.setattr(cli_parsing, "_DRACCUS_ATTRIBUTE_DOCSTRING",
                        lambda klass, name: asked.append((klass, name)) or original(klass, name))
    cli_parsing._attribute_docstring.cache_clear()
    _, memoized = _help("sr-train", monkeypatch, capsys)
    fields = len(asked)
    assert fields > 50 and len(set(asked)) == fields  # each (class, field) once, even in the first parse
    _help("sr-train", monkeypatch, capsys)
    assert len(asked) == fields  # the second parse asks draccus for nothing
    monkeypatch.setattr(docstring, "get_attribute_docstring", original)
    _, plain = _help("sr-train", monkeypatch, capsys)
    assert memoized == plain and "--sleep.lr" in plain
