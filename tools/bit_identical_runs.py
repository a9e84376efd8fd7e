"""Run the tiny ACT-SR and SAC streams (two skills each, a sleep after the second) that
``tools/check_bit_identical.sh`` compares across commits, and list the sha256 of every checkpoint they write.

Run from the root of the checkout under test (its ``sr_imitation``, ``tests`` and plugin first on ``PYTHONPATH``):

    python tools/bit_identical_runs.py DATASETS            # records the ACT stream's two datasets once
    python tools/bit_identical_runs.py DATASETS OUT        # the two runs

writes ``OUT/act`` and ``OUT/sac`` and ``OUT/sha256.txt``: one line ``<sha256>  <path>`` for every ``*.safetensors``
file, and for every JSON file of the runs (``results.json``, ``eval.json``, ``sleep_diagnostics.json``,
``settings_fingerprint.json``, ``checksums.json``, ...) the sha256 of its JSON with what names the commit, the
machine, a path or a time left out (those differ between any two runs). Both sides read the same recorded datasets
(a dataset recorded twice differs in its files' bytes, and the run's fingerprint holds their digest).
The runs are the test suite's tiny configurations (``tests/substrates/act/helpers.py``: ``tiny_stream_config`` with its
fake environment; ``tests/substrates/sac/test_trainer.py``: ``tiny_config``'s settings as ``sr-train --substrate=sac``
flags).
The substrates are imported from either package layout (before and after issue 61's move to
``sr_imitation/substrates/``), so one driver serves both sides of the comparison.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import sys
from pathlib import Path

ACT_SKILLS = ["approach", "place"]
SAC_FLAGS = [
    "--substrate=sac", "--seed=3", "--stream.skills=[reach-v3,door-open-v3]", "--max_episode_steps=30",
    "--sac.hidden_dim=32", "--sac.batch_size=16", "--sac.utd_ratio=0.5", "--sac.warmup_steps=40",
    "--sac.buffer_size=5000", "--wake.budget_scale=0.002", "--sleep.max_iterations=12",
    "--sleep.early_stop_window=5", "--sleep.fw_iterations=5", "--sleep.batch_size=16", "--memory.buffer_size=32",
    "--memory.validation_chunk=5", "--memory.validation_max_rounds=1", "--eval.episodes=2",
    "--eval.video_height=64", "--eval.video_width=64", "--progress=false", "--plots=false",
]
VOLATILE = ("time", "seconds", "commit", "git", "host", "date", "path", "dir", "root", "version_info", "python",
            "torch_version", "started", "finished", "elapsed", "duration", "sha256", "train_config.json")
"""Keys (by substring) left out of a JSON file's hash: they name when, where and from which commit it ran (a
checkpoint's ``train_config.json`` holds the run's paths: its entry in ``checksums.json`` too)."""


def only_the_checkout_under_test() -> None:
    """Drop the editable installs' import hooks (setuptools' finders map every ``sr_imitation.*`` name to the clone
    the venv was built from, even one the checkout under test lacks): the code comes from ``PYTHONPATH`` alone."""
    sys.meta_path[:] = [f for f in sys.meta_path if "__editable__" not in getattr(type(f), "__module__", "")]
    for name in [m for m in sys.modules if m == "sr_imitation" or m.startswith(("sr_imitation.", "lerobot_policy"))]:
        del sys.modules[name]


def _act_module(name: str):
    """``name`` of the ACT substrate in the checkout's layout (``substrates/act`` since issue 61, else
    ``imitation``)."""
    import sr_imitation

    moved = (Path(sr_imitation.__file__).parent / "substrates" / "act").is_dir()
    return importlib.import_module(f"sr_imitation.{'substrates.act' if moved else 'imitation'}.{name}")


def record_datasets(datasets: Path) -> None:
    from tests.substrates.act.helpers import make_skill_dataset

    for i, skill in enumerate(ACT_SKILLS):
        make_skill_dataset(datasets, skill, i, image=False)


def run_act(datasets: Path, out: Path) -> None:
    from tests.substrates.act.helpers import fake_env_factory, tiny_stream_config

    trainer = _act_module("trainer")
    trainer.train_stream(tiny_stream_config(datasets, out / "act", ACT_SKILLS, use_images=False), fake_env_factory)


def run_sac(out: Path) -> None:
    from sr_imitation import cli

    cli.train_main([*SAC_FLAGS, f"--output_dir={out / 'sac'}"])


def _stable(value):
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in sorted(value.items()) if not any(w in k.lower() for w in VOLATILE)}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def digests(out: Path) -> list[str]:
    lines = []
    for path in sorted(p for run in ("act", "sac") for p in (out / run).rglob("*") if p.is_file()):
        rel = path.relative_to(out)
        if path.suffix == ".safetensors":
            lines.append(f"{hashlib.sha256(path.read_bytes()).hexdigest()}  {rel}")
        elif path.suffix == ".json":
            stable = json.dumps(_stable(json.loads(path.read_text())), sort_keys=True).encode()
            lines.append(f"{hashlib.sha256(stable).hexdigest()}  {rel} (stable keys)")
    return lines


def main(argv: list[str]) -> None:
    import os

    datasets = Path(argv[0]).resolve()
    out = Path(argv[1]).resolve() if len(argv) > 1 else None
    scratch = out if out is not None else datasets.parent / f"{datasets.name}_recording"
    scratch.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ["HF_HOME"] = str(scratch / "hf_home")
    only_the_checkout_under_test()
    import torch

    torch.set_num_threads(1)
    import lerobot_policy_act_sr
    import sr_imitation

    for module in (sr_imitation, lerobot_policy_act_sr):
        if not Path(module.__file__).resolve().is_relative_to(Path.cwd().resolve()):
            raise SystemExit(f"{module.__name__} comes from {module.__file__}, not from the checkout under test")
    if out is None:
        record_datasets(datasets)
        return
    (out / "source.txt").write_text(f"{Path(sr_imitation.__file__).parent}\n")
    run_act(datasets, out)
    run_sac(out)
    (out / "sha256.txt").write_text("".join(f"{line}\n" for line in digests(out)))


if __name__ == "__main__":
    main(sys.argv[1:])
