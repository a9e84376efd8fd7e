"""sr_imitation.reporting.compare: two runs agree when every number they measured is equal (or within --tol), timings
aside; the command says where they differ and exits 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from sr_imitation.io import read_checked_json, write_checked_json
from sr_imitation.reporting.compare import compare_runs, leaves, main
from tests.stream.conftest import make_engine


@pytest.fixture
def runs(tmp_path) -> dict[str, Path]:
    for name, seed in (("a", 0), ("b", 0), ("other_seed", 1)):
        make_engine(tmp_path / "runs" / name, seed=seed).run()
    return {p.name: p for p in (tmp_path / "runs").iterdir()}


def test_leaves_paths_every_value_of_nested_dicts_and_lists():
    assert list(leaves({"b": [1, {"c": 2}], "a": 3.0})) == [("a", 3.0), ("b[0]", 1), ("b[1].c", 2)]


def test_two_runs_of_the_same_settings_agree_and_another_seed_does_not(runs, capsys):
    same = compare_runs(runs["a"], runs["b"])
    assert same["compared"] > 20 and same["differences"] == [] and same["max_diff"] == 0.0
    assert main([str(runs["a"]), str(runs["b"])]) == 0
    assert "the runs agree; every number equal" in capsys.readouterr().out
    other = compare_runs(runs["a"], runs["other_seed"])
    assert other["differences"] and other["max_diff"] > 0
    assert main([str(runs["a"]), str(runs["other_seed"])]) == 1
    assert "the runs differ in" in capsys.readouterr().out


def test_timings_are_not_compared_and_a_changed_number_is_found_within_tol_or_not(runs, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(runs["a"], copy)
    progress = read_checked_json(copy / "progress.json")
    phase = next(k for k in progress["completed"] if k.endswith(".sleep"))
    for record in progress["completed"].values():
        record["seconds"] = 1e6  # another machine's clock: still the same run
    write_checked_json(copy / "progress.json", progress)
    assert compare_runs(runs["a"], copy)["differences"] == []
    losses = progress["completed"][phase]["final_memory_losses"]
    losses[0] += 1e-9
    write_checked_json(copy / "progress.json", progress)
    report = compare_runs(runs["a"], copy)
    assert [d[0] for d in report["differences"]] == [f"progress:{phase}.final_memory_losses[0]"]
    assert compare_runs(runs["a"], copy, tol=1e-8)["differences"] == []
    del progress["completed"][phase]
    write_checked_json(copy / "progress.json", progress)
    assert compare_runs(runs["a"], copy)["only_a"]


def test_results_files_are_compared_too(runs, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(runs["a"], a)
    shutil.copytree(runs["a"], b)
    results = {"results_version": 5, "success_matrix_per_unit": [[[1.0]], [[0.5]]],
               "metrics": {"afsr": {"final": 0.75}}, "stages": [{"wake": {"seconds": 3.0}}],
               "config": {"output_dir": "x"}}
    write_checked_json(a / "results.json", results)
    results |= {"stages": [{"wake": {"seconds": 9.0}}], "config": {"output_dir": "y"}}  # neither is a measurement
    write_checked_json(b / "results.json", results)
    assert compare_runs(a, b)["differences"] == []
    results["success_matrix_per_unit"][1][0][0] = 0.6
    write_checked_json(b / "results.json", results)
    assert [d[0] for d in compare_runs(a, b)["differences"]] == ["results:success_matrix_per_unit[1][0][0]"]


def test_a_results_file_that_does_not_match_its_seal_is_refused_not_compared(runs, tmp_path, capsys):
    """Before: "the runs agree" after a digit of one run's results.json was flipped."""
    from sr_imitation.infra.cli_errors import run_cli

    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(runs["a"], a)
    for run in (a, b):
        if run is b:
            shutil.copytree(a, b)
        write_checked_json(run / "results.json", {"results_version": 5, "metrics": {"afsr": {"final": 0.5}}})
    path = b / "results.json"
    text = path.read_text()
    at = text.index('"final": ') + len('"final": ')
    path.write_text(text[:at] + ("2" if text[at] != "2" else "3") + text[at + 1:])  # one flipped digit
    with pytest.raises(SystemExit) as exc:
        run_cli("sr_imitation.reporting.compare", main, [str(a), str(b)])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and f"{path}: contents do not match its sha256" in err


@pytest.mark.parametrize("run_a", [True, False])
def test_a_folder_without_runs_is_one_line(runs, run_a, tmp_path, capsys):
    from sr_imitation.infra.cli_errors import run_cli

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit) as exit_:
        run_cli("sr_imitation.reporting.compare", main, [str(runs["a"] if run_a else empty), str(empty)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert ("not a run directory (no progress.json)" if run_a else "no run here") in err


def test_two_folders_of_runs_are_compared_run_by_run(runs, tmp_path, capsys):
    a, b = tmp_path / "grid_a", tmp_path / "grid_b"
    for folder in (a, b):
        shutil.copytree(runs["a"], folder / "sr_seed0")
    assert main([str(a), str(b)]) == 0
    assert "| sr_seed0 |" in capsys.readouterr().out
    shutil.copytree(runs["other_seed"], b / "sr_seed1")
    assert main([str(a), str(b)]) == 1
    assert "| sr_seed1 | - | - | - | only in B |" in capsys.readouterr().out
    shutil.rmtree(b / "sr_seed0")
    shutil.copytree(runs["other_seed"], b / "sr_seed0")
    shutil.copytree(runs["other_seed"], a / "sr_seed1")
    assert main([str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "| sr_seed0 |" in out and out.count("differ |") == 1 and out.count("agree |") == 1


def test_runs_that_have_measured_nothing_yet_do_not_agree(tmp_path, capsys):
    from sr_imitation.infra.fingerprint import settings_fingerprint, write_fingerprint

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        write_fingerprint(tmp_path / name / "settings_fingerprint.json", settings_fingerprint({"seed": 0}))
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    assert "0 measured values compared: nothing measured yet" in capsys.readouterr().out


def test_the_code_that_wrote_each_run_is_named(runs, tmp_path):
    from sr_imitation.reporting.compare import run_commit

    assert run_commit(runs["a"]) == "unknown commit"  # the toy writes no results.json
    (tmp_path / "results.json").write_text(json.dumps({"code": {"commit": "0123456789abcdef", "dirty": True}}))
    assert run_commit(tmp_path) == "commit 0123456789 (dirty)"


def test_a_run_whose_train_config_was_edited_is_refused_not_compared(tmp_path, capsys):
    """Every seal a resume checks, compare checks: a ``train_config.json`` edited after it was sealed, or an unsealed
    one (renamed seal) that differs from the run's fingerprint, is one line naming the file, exit 2. Before:
    "settings: the same" and "the runs agree", exit 0."""
    from sr_imitation.infra.cli_errors import run_cli
    from tests.stream import toy

    for name in ("a", "b"):
        toy.main(["--stream.skills=[a,b]", "--progress=false", "--wake_steps=10", f"--output_dir={tmp_path / name}"])
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert "settings: the same" in capsys.readouterr().out
    path = tmp_path / "b" / "train_config.json"
    sealed = path.read_text()
    assert '"wake_steps": 10' in sealed
    unsealed = {k: v for k, v in json.loads(sealed).items() if k != "sha256"} | {"wake_steps": 11}
    edits = {"sealed": sealed.replace('"wake_steps": 10', '"wake_steps": 11'),  # the seal no longer matches
             "unsealed": json.dumps(unsealed)}  # as if written before seals, then edited
    for what, text in edits.items():
        path.write_text(text)
        with pytest.raises(SystemExit) as exc:
            run_cli("sr_imitation.reporting.compare", main, [str(tmp_path / "a"), str(tmp_path / "b")])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and f"{path}: " in err, what
        assert ("contents do not match its sha256" if what == "sealed" else
                "differs from settings_fingerprint.json in wake_steps") in err, what
