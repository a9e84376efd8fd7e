"""The code version results record: the git commit of the running checkout, nothing outside one."""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path

import pytest

from sr_imitation.infra.provenance import PACKAGE_ROOT, code_version, log_code_version, process_code_version


def _git(root, *args):
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True).stdout.strip()


def test_code_version_names_the_commit_and_whether_tracked_files_changed(tmp_path):
    assert code_version(tmp_path) == {"commit": None, "dirty": None}  # not a checkout (an installed wheel)
    repo = tmp_path / "repo"
    repo.mkdir()
    try:
        _git(repo, "init", "-q")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("git is not available")
    (repo / "sr_imitation").mkdir()
    (repo / "sr_imitation" / "f.py").write_text("a")
    (repo / "notes.md").write_text("a")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x")
    head = _git(repo, "rev-parse", "HEAD")
    assert code_version(repo) == {"commit": head, "dirty": False}
    (repo / "sr_imitation" / "new.py").write_text("untracked files do not count")
    (repo / "notes.md").write_text("nor do changes outside the code (docs, results)")
    assert code_version(repo)["dirty"] is False
    (repo / "sr_imitation" / "f.py").write_text("b")
    assert code_version(repo) == {"commit": head, "dirty": True}


def test_the_package_root_holds_the_package():
    assert (PACKAGE_ROOT / "sr_imitation" / "infra" / "provenance.py").is_file()


def test_the_process_takes_its_code_version_once():
    assert process_code_version() is process_code_version()
    assert process_code_version() == code_version()  # nothing changed the checkout during the test


def test_a_run_logs_the_code_version_it_records(caplog):
    logger = logging.getLogger("sr_imitation.test_provenance")
    with caplog.at_level(logging.INFO, logger=logger.name):
        code = log_code_version(logger)
    assert code is process_code_version()
    assert f"code: commit {code['commit'] or 'unknown'}" in caplog.text


def test_the_library_caps_a_run_records_are_the_isa_variables_set_and_only_those():
    from sr_imitation.infra.provenance import LIBRARY_ISA_VARIABLES, library_caps
    assert library_caps({}) == {}
    env = {"MKL_ENABLE_INSTRUCTIONS": "AVX2", "NPY_DISABLE_CPU_FEATURES": "AVX512F AVX512CD", "PATH": "/bin",
           "OPENBLAS_CORETYPE": ""}  # an empty variable leaves the library its choice: not a cap
    assert library_caps(env) == {"MKL_ENABLE_INSTRUCTIONS": "AVX2", "NPY_DISABLE_CPU_FEATURES": "AVX512F AVX512CD"}
    # the variables tools/experiments/isa_env.sh sets are all recorded
    script = (Path(__file__).resolve().parents[2] / "tools" / "experiments" / "isa_env.sh").read_text()
    assert {v for v in LIBRARY_ISA_VARIABLES if f"{v}=" in script} == set(LIBRARY_ISA_VARIABLES) - {"MKL_CBWR"}


def test_a_run_logs_the_library_caps_it_runs_under(caplog, monkeypatch):
    from sr_imitation.infra.provenance import LIBRARY_ISA_VARIABLES
    for name in LIBRARY_ISA_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    with caplog.at_level(logging.INFO):
        log_code_version(logging.getLogger("test"))
    assert caplog.records[-1].getMessage().endswith("; libraries: ATEN_CPU_CAPABILITY=avx2")
