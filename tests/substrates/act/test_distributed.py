"""Several processes for one ``sr-train`` run (sr_imitation.infra.distributed): two CPU processes (gloo, started by
``torchrun``) give the one-process run's results with the same batch, up to float summation order, and only the main
process writes the run directory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from sr_imitation.cli import train_main
from sr_imitation.infra.distributed import Processes, shard
from sr_imitation.substrates.act.config import stored_config_dict
from sr_imitation.substrates.act.evaluate import EvalConfig
from tests.substrates.act.helpers import tiny_stream_config

SKILLS = ["approach", "place"]
TOLERANCE = 1e-4
"""Largest absolute difference allowed between a weight (or a reported loss) of the two-process run and of the
one-process run: the same steps, the batch's gradient summed in another order (measured on this tiny stream, 2026-11-25:
largest difference 1e-5 over 214 saved tensors, 120 of them bit-identical; Adam's step divides by sqrt(v), which
magnifies the reordering in gradient entries near zero)."""


def test_shard_cuts_contiguous_slices_and_their_shares():
    batch = {"x": torch.arange(5), "names": list("abcde"), "flag": True}
    first, share0 = shard(batch, Processes(0, 2))
    second, share1 = shard(batch, Processes(1, 2))
    assert first["x"].tolist() == [0, 1, 2] and second["x"].tolist() == [3, 4] and second["names"] == ["d", "e"]
    assert (share0, share1) == (0.6, 0.4) and first["flag"] is True
    small, share = shard({"x": torch.arange(1)}, Processes(1, 2))  # fewer rows than processes: all of it, 1/N each
    assert small["x"].tolist() == [0] and share == 0.5
    assert shard(batch, Processes())[1] == 1.0
    with pytest.raises(ValueError, match="different lengths"):
        shard({"x": torch.arange(2), "y": torch.arange(3)}, Processes(0, 2))


def _torchrun(config: Path, out: Path, tmp: Path) -> subprocess.CompletedProcess:
    """``sr-train`` on ``config`` as two processes started by ``torchrun``, ``tmp`` their temporary folder."""
    cli = ["-m", "sr_imitation.cli", f"--config_path={config}", f"--output_dir={out}"]
    launcher = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TMPDIR": str(tmp)}
    return subprocess.run([sys.executable, *launcher, *cli], capture_output=True, text=True, env=env, timeout=600)


@pytest.mark.slow
def test_two_processes_give_the_one_process_run_and_write_it_once(state_datasets, tmp_path):
    cfg = tiny_stream_config(state_datasets, tmp_path / "unused", SKILLS, use_images=False, dropout=0.0,
                             use_vae=False)
    cfg.eval = EvalConfig(env="none", episodes=0)
    config = tmp_path / "train_config.json"
    config.write_text(json.dumps(stored_config_dict(cfg)))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the one-process reference in this process: sr-train's entry, one thread as each rank
    try:
        train_main([f"--config_path={config}", f"--output_dir={tmp_path / 'run1'}"])
    finally:
        torch.set_num_threads(threads)
    scratch = tmp_path / "tmp2"
    scratch.mkdir()
    done = _torchrun(config, tmp_path / "run2", scratch)
    assert done.returncode == 0, done.stderr[-3000:]
    # the other process's scratch copy is gone (torchrun keeps its own torchelastic_* folder there)
    assert [p.name for p in scratch.iterdir() if not p.name.startswith("torchelastic_")] == []
    runs = {n: tmp_path / f"run{n}" for n in (1, 2)}
    files = {n: sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file()) for n, run in runs.items()}
    assert files[1] == files[2]  # the same files, once: the second process wrote none of the run's
    log = (runs[2] / "log.jsonl").read_text().splitlines()
    assert sum('"phase": "wake"' in line and '"kind": "phase"' in line for line in log) <= len(SKILLS)
    weights = [p for p in files[1] if p.endswith(".safetensors")]
    assert any("sleep/pretrained_model" in p for p in weights)
    for name in weights:
        one, two = load_file(runs[1] / name), load_file(runs[2] / name)
        assert one.keys() == two.keys(), name
        for key in one:
            assert torch.allclose(one[key].double(), two[key].double(), atol=TOLERANCE, rtol=0), (name, key)
    losses = [json.loads((run / "results.json").read_text())["losses"] for run in runs.values()]
    for key in ("memory_loss", "validation_l1"):
        a = torch.tensor([[v if v is not None else 0.0 for v in row] for row in losses[0][key]], dtype=torch.float64)
        b = torch.tensor([[v if v is not None else 0.0 for v in row] for row in losses[1][key]], dtype=torch.float64)
        assert torch.allclose(a, b, atol=TOLERANCE, rtol=0), key


def test_too_small_a_batch_for_the_processes_is_one_line(state_datasets, tmp_path):
    cfg = tiny_stream_config(state_datasets, tmp_path / "unused", SKILLS, use_images=False)
    cfg.eval = EvalConfig(env="none", episodes=0)
    cfg.wake.batch_size = 1
    config = tmp_path / "train_config.json"
    config.write_text(json.dumps(stored_config_dict(cfg)))
    done = _torchrun(config, tmp_path / "run", tmp_path)
    assert done.returncode != 0 and "wake.batch_size: 1 rows cannot be split over 2 processes" in done.stderr
    assert not (tmp_path / "run").exists()


def test_a_killed_process_s_scratch_folder_is_removed_at_the_next_start(tmp_path):
    """Before: a rank killed mid-run left its scratch copy of the run in the temporary folder for good."""
    import os
    import subprocess
    import sys

    from sr_imitation.infra.distributed import SCRATCH_PREFIX, remove_stale_scratch

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    dead = tmp_path / f"{SCRATCH_PREFIX}1-pid{int(gone.stdout)}-abc"
    alive = tmp_path / f"{SCRATCH_PREFIX}1-pid{os.getpid()}-def"
    other = tmp_path / f"{SCRATCH_PREFIX}1-xyz"  # no process id: not known to be ours
    for folder in (dead, alive, other):
        (folder / "run").mkdir(parents=True)
    assert remove_stale_scratch(tmp_path) == [dead]
    assert not dead.exists() and alive.is_dir() and other.is_dir()
