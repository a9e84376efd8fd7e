"""Every command README.md and the user-facing docs pages show is run by a test, or, where it is a whole experiment,
parsed by its program's own parser up to the point where work starts.

The commands are each page's ```bash blocks (continuation lines joined, comments dropped, by the extractor
``tools/check_readme_routes.py`` uses to run README's routes on a fresh clone) and README's inline code spans that
start with a program. Each is listed once below: in :data:`RUN_BY` with the test that runs it (that test must exist
and name the program), or in :data:`PARSED` (too long to run here). A command added to a page and in neither list
fails :func:`test_every_command_the_pages_show_is_run_or_parsed`; a listed command no page shows any more fails it
too. Every command of a program with a parser is also parsed (:func:`dry_parse`), the run ones included."""

from __future__ import annotations

import ast
import contextlib
import importlib
import re
import shlex
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import draccus
import pytest

from tests.tool_loader import load_tool

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *(f"docs/{name}" for name in (
    "COMMANDS.md", "ARCHITECTURE.md", "BENCHMARKS.md", "EVIDENCE.md", "NEEDLE_ENV.md")), "configs/README.md",
         "policies/README.md"]
"""The user-facing pages (the dated records, docs/RESULTS.md and docs/results/, keep the commands of their day)."""
PROGRAMS = ("sr-", "lerobot-", "bash ", "python ", "pip ", "torchrun ", "accelerate ", "ray ", "source ")
"""How an inline code span that is a command starts."""
STOCK = ("tests/substrates/act/test_stock_route.py::"
         "test_readmes_stock_route_writes_each_skills_memory_and_sleeps_and_evaluates_both")
PIP = "tests/test_install.py::test_pip_install_into_an_existing_lerobot_environment"
_README_ROUTE = load_tool("check_readme_routes")
_ROUTE = [" ".join(shlex.split(c)) for c in _README_ROUTE.bash_blocks_after(
    (ROOT / "README.md").read_text(), "**The LeRobot workflow", 1)[0]]

RUN_BY: dict[str, tuple[str, str]] = {
    # command: (the test that runs it, a word its source must hold)
    "bash .ci/test.sh": ("tests/test_ci_dist.py::"
                         "test_the_readme_command_keeps_temporary_files_on_a_ram_disk_when_there_is_one",
                         ".ci/test.sh"),  # the suite's own runner; this test checks it ran the suite
    "pip install ./ ./policies/lerobot_policy_act_sr ./policies/lerobot_env_sr": (PIP, '"install"'),
    "pip check": (PIP, '"check"'),
    "source .venv/bin/activate": ("tests/test_install.py::test_two_clones_each_run_their_own_code_over_one_shared_venv",
                                  "venv.sh"),
    **dict.fromkeys(_ROUTE, (STOCK, "stock_route()")),  # README's stock route, read from README there
}
PARSED: set[str] = {
    # README
    "bash .ci/main.sh",  # the main job (two needle runs); its dispatch: tests/test_main_job_compare.py
    "bash .ci/main.sh --train.resume=true",
    "bash .ci/main.sh --config_path=configs/needle_cpu.json",
    "sr-main --config_path=configs/needle_try.json",  # five minutes
    "sr-train --stream.skills=[pick,place_cup] --stream.repo_ids=[user/pick,user/place_cup] --eval.env=none "
    "--output_dir=outputs/mine",  # a user's datasets (tools/check_readme_routes.py runs both on a fresh clone)
    "sr-train --stream.skills=[pick,place_cup] --stream.dataset_paths=[data/pick,data/place_cup] --eval.env=gym "
    "--eval.gym_ids=[my_pkg/Pick-v0,my_pkg/PlaceCup-v0] --output_dir=outputs/mine_gym",
    "sr-grid --preset=my_skills.json --variants=[sr,wake_only] --seeds=[0,1,2,3,4] --output_root=outputs/my_grid",
    "python -m sr_imitation.experiments.hypotheses --archive=outputs/my_grid --tests=[sr>wake_only] "
    "--output=outputs/my_grid/hypotheses",
    # docs/COMMANDS.md
    "lerobot-train --policy.type=act_sr --policy.sleep=true --policy.push_to_hub=false "
    "--dataset.repo_id=local/sr_needle_approach --dataset.root=datasets/needle/approach --output_dir=outputs/approach",
    "sr-grid --preset=configs/needle_cpu_m16.json --variants=[sr,wake_only,sequential_bc] --seeds=[0,1,2] "
    "--output_root=outputs/needle_grid --archive=docs/results/needle_cpu_m16_compare",
    "sr-grid --preset=configs/sac_mt5_cpu.json --variants=[sr,wake_only,ewc] --seeds=[0,1] "
    "--output_root=outputs/mt5_grid",
    "sr-grid --preset=configs/needle_cpu_m16.json --variants=[sr,wake_only] --seeds=[0,1,2] "
    "--output_root=outputs/needle_grid --summary_only=true",
    "ray start --head --port=6379",
    "ray start --address=<head>:6379",
    "sr-grid --preset=configs/needle_paper.json --variants=[sr,wake_only] --seeds=[0,1,2,3,4] "
    "--output_root=/shared/needle_paper_grid --ray.address=auto --ray.num_cpus=4 --ray.num_gpus=1 --ray.memory_gb=16",
    "torchrun --standalone --nproc_per_node=2 -m sr_imitation.cli --config_path=configs/needle_cpu.json "
    "--output_dir=outputs/needle_2proc",  # tests/substrates/act/test_distributed.py runs torchrun on a tiny stream
    "accelerate launch --multi_gpu --num_processes=2 -m sr_imitation.cli --config_path=configs/needle_cpu.json "
    "--policy.device=cuda --output_dir=outputs/needle_2gpu",
    "sr-train --config_path=configs/sac_mt5_cpu.json --seed=0 --output_dir=outputs/sac_cpu_s0",
    "sr-train --config_path=configs/sac_mt5_cpu.json --output_dir=outputs/sac_cpu_s0 --resume=true",
    "sr-train --config_path=configs/sac_mt5_cpu.json --sleep.enabled=false --output_dir=outputs/wake_only_s0",
    "sr-train --config_path=configs/sac_mt5_paper.json --stream.name=mt5-reverse",
    "sr-train --config_path=configs/sac_mt5_cpu.json --stream.name=mt8 --stream.extend_from=outputs/sac_cpu_s1 "
    "--output_dir=outputs/sac_cpu_s1_mt8",
    "sr-sac-sleep --source=docs/results/sac_sleep_calibration.weights/sr_seed100 "
    "--archived=docs/results/sac_sleep_calibration/sr_seed100 --output_dir=outputs/resleep/a1_seed100 "
    "--changes=[--sleep.early_stop_tol=0,--eval.videos_per_skill=0]",
    # policies/README.md (LeRobot's default ACT, 20 000 steps)
    "lerobot-train --policy.type=act_sr --policy.sleep=true --policy.push_to_hub=false --policy.device=cpu "
    "--dataset.repo_id=local/sr_needle_approach --dataset.root=datasets/needle/approach "
    "--dataset.video_backend=pyav --steps=20000 --batch_size=8 --output_dir=outputs/approach",
    # docs/BENCHMARKS.md
    "PYTHONPATH=. MUJOCO_GL=egl HF_HUB_OFFLINE=1 python -m sr_imitation.benchmarks.needle_env --record_episodes=100 "
    "--output=outputs/needle_bench_100.json",
}
"""Whole experiments: parsed by :func:`dry_parse`, not run."""


def shown_commands() -> dict[str, str]:
    """Every command the pages show (as :func:`shlex.split` reads it, rejoined), with the first page showing it."""
    shown: dict[str, str] = {}
    for page in PAGES:
        text = (ROOT / page).read_text()
        blocks = _README_ROUTE.bash_blocks_after(text, "", text.count("```bash")) if "```bash" in text else []
        spans = [s for s in re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
                 if s.startswith(PROGRAMS) and " " in s.strip()] if page == "README.md" else []
        for command in [c for block in blocks for c in block] + spans:
            shown.setdefault(" ".join(shlex.split(command)), page)
    return shown


def test_every_command_the_pages_show_is_run_or_parsed():
    shown = shown_commands()
    assert not set(RUN_BY) & PARSED
    assert sorted(c for c in shown if c not in RUN_BY and c not in PARSED) == []  # a new command: run or parse it
    assert sorted(c for c in [*RUN_BY, *PARSED] if c not in shown) == []  # a command the pages no longer show
    assert len(_ROUTE) == 5 and all(c in shown for c in _ROUTE)


@pytest.mark.parametrize("node", sorted({node for node, _ in RUN_BY.values()}))
def test_each_test_named_as_running_a_command_exists_and_runs_its_program(node):
    path, name = node.split("::")
    source = (ROOT / path).read_text()
    (function,) = [f for f in ast.walk(ast.parse(source)) if isinstance(f, ast.FunctionDef) and f.name == name]
    body = ast.get_source_segment(source, function)
    for command, (where, word) in RUN_BY.items():
        if where == node:
            assert word in body, (command, word)


# -- parsing a command as its program does, stopping where work would start --------------------------------------
class Parsed(Exception):  # noqa: N818 (not an error: how a dry parse stops)
    """Raised where a command would start working, holding what its parser made."""

    def __init__(self, value: object) -> None:
        super().__init__("parsed")
        self.value = value


@contextlib.contextmanager
def _stop(module: str, name: str, after: bool) -> Iterator[None]:
    """``module.name`` replaced: with ``after`` it is called, then :class:`Parsed` of its result is raised; without,
    :class:`Parsed` of its arguments, before it runs."""
    mod = importlib.import_module(module)
    real = getattr(mod, name)

    def stop(*args, **kwargs):
        raise Parsed(real(*args, **kwargs) if after else args)

    setattr(mod, name, stop)
    try:
        yield
    finally:
        setattr(mod, name, real)


def _up_to(module: str, main: str, stop_at: str, *, after: bool = False,
           also: tuple[str, str, bool] | None = None) -> Callable[[list[str]], object]:
    """A command's own ``main`` run on ``args`` until it reaches ``stop_at`` (its first work, or its parser) or
    ``also`` ((module, name, after) of another route through it)."""
    def run(args: list[str]) -> object:
        with contextlib.ExitStack() as stack:
            stack.enter_context(_stop(module, stop_at, after))
            if also is not None:
                stack.enter_context(_stop(*also))
            stopped = stack.enter_context(pytest.raises(Parsed))
            getattr(importlib.import_module(module), main)(args)
        return stopped.value.value
    return run


def _sr_train(args: list[str]) -> object:
    from sr_imitation.cli import parse_args

    return parse_args(args)


def _main_sh(args: list[str]) -> object:
    """.ci/main.sh: sr-main with --config_path, else the comparison job (tests/test_main_job_compare.py checks it)."""
    if any(a.startswith("--config_path=") for a in args):
        return PARSERS["sr-main"](args)
    return _up_to("sr_imitation.experiments.main_compare", "main", "run_main_compare")(args)


def _lerobot_train(args: list[str]) -> object:
    from lerobot.configs.train import TrainPipelineConfig

    import lerobot_policy_act_sr  # noqa: F401 (registers act_sr, as LeRobot's plugin discovery does)

    assert not any(a.startswith("--policy.path=") for a in args), "a run from --policy.path is run, not parsed"
    return draccus.parse(TrainPipelineConfig, args=args)


def _module(args: list[str]) -> object:
    """``python -m <module> ...``."""
    assert args[0] == "-m", args
    return PARSERS[f"python -m {args[1]}"](args[2:])


def _launcher(parser: Callable[[], object]) -> Callable[[list[str]], object]:
    """``torchrun`` / ``accelerate launch``: the launcher's own parser, then the module's command line."""
    def run(args: list[str]) -> object:
        launched = parser().parse_args(args)
        assert launched.module, args
        return PARSERS[f"python -m {launched.training_script}"](launched.training_script_args)
    return run


def _torchrun() -> object:
    from torch.distributed.run import get_args_parser

    return get_args_parser()


def _accelerate() -> object:
    from accelerate.commands.launch import launch_command_parser

    return launch_command_parser()


def _ray(args: list[str]) -> object:
    from ray.scripts.scripts import cli

    (name, *rest) = args
    return cli.commands[name].make_context(f"ray {name}", rest).params


PARSERS: dict[str, Callable[[list[str]], object]] = {
    "sr-train": _sr_train,
    "python -m sr_imitation.cli": _sr_train,
    "sr-main": _up_to("sr_imitation.main_job", "main", "run_main_job"),
    "sr-record": _up_to("sr_imitation.recorders.needle", "main", "report_recorded"),  # the needle recorder
    "sr-record --env=metaworld": _up_to("sr_imitation.recorders.cli", "main", "report_recorded", after=True,
                                        also=("sr_imitation.recorders.metaworld", "parse_command", True)),
    "sr-grid": _up_to("sr_imitation.experiments.grid", "main", "run_grid"),
    "sr-sleep": _up_to("sr_imitation.substrates.act.cli", "sleep_main", "hold_folder"),
    "sr-sac-sleep": _up_to("sr_imitation.substrates.sac.resleep", "main", "resleep"),
    "python -m sr_imitation.experiments.hypotheses": _up_to("sr_imitation.experiments.hypotheses", "main",
                                                            "run_tests"),
    "python -m sr_imitation.benchmarks.needle_env": _up_to("sr_imitation.benchmarks.needle_env", "main",
                                                           "parse_command", after=True),
    "bash .ci/main.sh": _main_sh,
    "lerobot-train": _lerobot_train,
    "python": _module,
    "torchrun": _launcher(_torchrun),
    "accelerate launch": _launcher(_accelerate),
    "ray": _ray,
}
"""Each program's parser, run to where the program would start working."""


def dry_parse(command: str) -> object:
    """What ``command``'s program makes of it (environment assignments in front are left out)."""
    argv = shlex.split(command)
    while re.match(r"^[A-Z_]+=", argv[0]):
        argv = argv[1:]
    if argv[0] == "sr-record" and "--env=metaworld" in argv:
        return PARSERS["sr-record --env=metaworld"](argv[1:])
    for length in (3, 2, 1):
        program = " ".join(argv[:length])
        if program in PARSERS and (length > 1 or program not in ("python", "bash")):
            return PARSERS[program](argv[length:])
    raise AssertionError(f"no parser for {command!r}")


def _parseable(command: str) -> bool:
    return not command.startswith(("pip ", "source ", "bash .ci/test.sh", "lerobot-eval ")) and \
        "--policy.path=" not in command


@pytest.fixture
def user_folder(tmp_path, monkeypatch) -> Path:
    """A folder like a user's clone: the repository's configs and docs, and ``my_skills.json`` (an sr-train preset)."""
    for name in ("configs", "docs"):
        (tmp_path / name).symlink_to(ROOT / name)
    shutil.copy(ROOT / "configs" / "needle_cpu_m16.json", tmp_path / "my_skills.json")
    (tmp_path / "outputs" / "my_grid").mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("command", sorted(c for c in [*PARSED, *RUN_BY] if _parseable(c)))
def test_each_command_parses_as_its_program_parses_it(command, user_folder):
    assert dry_parse(command) is not None
    assert not (user_folder / "outputs").exists() or [p.name for p in (user_folder / "outputs").iterdir()] == [
        "my_grid"]  # nothing written


def test_every_parsed_command_has_a_parser():
    assert all(_parseable(c) for c in PARSED)


# -- README's stock route: what LeRobot checks in seconds ------------------------------------------------------------
@pytest.fixture(scope="module")
def stock_route() -> list[list[str]]:
    return [shlex.split(command) for command in _ROUTE]


def test_the_stock_route_is_the_whole_workflow(stock_route):
    assert [argv[0] for argv in stock_route] == ["sr-record", "lerobot-train", "lerobot-train", "sr-sleep",
                                                 "lerobot-eval"]


def test_lerobot_eval_accepts_the_stock_routes_evaluation_flags(stock_route):
    from lerobot.configs.default import EvalConfig

    for argv in stock_route:
        if argv[0] == "lerobot-eval":
            flags = ["--" + a.removeprefix("--eval.") for a in argv[1:] if a.startswith("--eval.")]
            cfg = draccus.parse(EvalConfig, args=flags)  # LeRobot's own checks run in its __post_init__
            assert cfg.batch_size <= cfg.n_episodes


def test_lerobot_train_parses_the_first_wake_as_the_cpu_presets_small_act(stock_route):
    from lerobot.configs.train import TrainPipelineConfig

    from lerobot_policy_act_sr import ACTSRConfig  # registers act_sr, as LeRobot's plugin discovery does

    first = next(argv for argv in stock_route if argv[0] == "lerobot-train")
    cfg = draccus.parse(TrainPipelineConfig, args=first[1:])
    assert isinstance(cfg.policy, ACTSRConfig) and cfg.policy.sleep and not cfg.policy.use_images
    assert (cfg.policy.dim_model, cfg.batch_size, cfg.steps) == (128, 32, 2000)


def test_sleep_flag_on_each_command_does_what_readme_says(capsys):
    """README: ``--policy.sleep=true`` is ``--sleep.enabled=true`` on sr-train; sr-sleep does not take it. (What it does
    on lerobot-train, from --policy.path too, and that lerobot-eval saves nothing: tests/substrates/act/
    test_stock_route.py.)"""
    from sr_imitation.infra.cli_errors import run_cli
    from sr_imitation.substrates.act.cli import sleep_main

    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "on `sr-train` it is the same switch as `--sleep.enabled=true`" in readme
    assert "`sr-sleep` always sleeps and does not take the flag" in readme
    assert "on `lerobot-train` it writes the skill's frozen memory into every checkpoint (from `--policy.path` too" \
        in readme and "`lerobot-eval` reads it from the checkpoint and only evaluates" in readme
    args = ["--stream.skills=[a,b]", "--stream.dataset_paths=[x,y]", "--eval.env=none"]
    assert _sr_train([*args, "--policy.sleep=true"]).sleep.enabled is True
    assert _sr_train([*args, "--policy.sleep=false"]).sleep.enabled is False
    with pytest.raises(SystemExit) as exit_info:
        run_cli("sr-sleep", sleep_main, ["--policy.path=p", "--policy.sleep=true", "--memories=[m]"])
    assert exit_info.value.code == 2 and "unknown flag --policy.sleep" in capsys.readouterr().err
