"""Settings fingerprints (core): flattening, allow-lists, digests, diffs, the one-line error, the stored file.

The helpers at the bottom (``leaves``, ``changed_values``, ``tree_state``) are shared with the resume-settings
property tests of both programs (tests/substrates/act/test_resume_settings.py,
tests/substrates/sac/test_resume_settings.py).
"""

from __future__ import annotations

import copy
import enum
import hashlib
import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from sr_imitation.infra.fingerprint import (
    ABSENT,
    FINGERPRINT_FILE,
    SettingsFingerprint,
    SettingsMismatchError,
    canonical_json,
    check_settings,
    diff_settings,
    flatten_settings,
    is_allowed,
    output_dir_for,
    read_fingerprint,
    settings_digest,
    settings_fingerprint,
    write_fingerprint,
)
from sr_imitation.io import CorruptFileError


class Mode(enum.Enum):
    A = "a"
    B = "b"


@dataclass
class Budget:
    max_episodes: int = 10
    patience: int = 3


@dataclass
class Inner:
    lr: float = 1e-3
    mode: Mode = Mode.A
    shape: tuple[int, ...] = (3, 4)
    budgets: dict[str, Budget] = field(default_factory=lambda: {"reach": Budget()})
    features: dict[str, Budget] = field(default_factory=dict)
    tau: float | None = None


@dataclass
class Outer:
    output_dir: Path = Path("/abs/run")
    seed: int = 1
    skills: list[str] = field(default_factory=lambda: ["a", "b"])
    inner: Inner = field(default_factory=Inner)
    progress: bool = True
    wandb: dict[str, Any] = field(default_factory=lambda: {"enable": False, "project": "x"})


def test_flatten_walks_dataclasses_and_mappings_into_dotted_json_leaves():
    flat = flatten_settings(Outer())
    assert flat == {
        "output_dir": "/abs/run", "seed": 1, "skills": ["a", "b"], "progress": True,
        "inner.lr": 1e-3, "inner.mode": "a", "inner.shape": [3, 4], "inner.tau": None,
        "inner.budgets.reach.max_episodes": 10, "inner.budgets.reach.patience": 3,
        "inner.features": {},  # an empty mapping is a leaf: adding its first entry is a change
        "wandb.enable": False, "wandb.project": "x",
    }
    json.dumps(flat)  # JSON-able throughout
    # A mapping works as well as a dataclass (the programs pass draccus-ready dicts).
    assert flatten_settings({"policy": {"type": "act_sr", "lr": 1}, "seed": 2}) == {"policy.type": "act_sr",
                                                                                  "policy.lr": 1, "seed": 2}


def test_flatten_refuses_what_it_cannot_represent():
    with pytest.raises(TypeError, match="'inner.lr': cannot fingerprint a value of type object"):
        flatten_settings({"inner": {"lr": object()}})
    with pytest.raises(ValueError, match="'a.b' appears twice"):
        flatten_settings({"a.b": 1, "a": {"b": 2}})
    with pytest.raises(TypeError, match="dataclass or a mapping"):
        flatten_settings(3)


def test_allow_list_patterns_cover_the_keys_below_them_and_nothing_else():
    allow = ("output_dir", "progress", "wandb.*", "inner.budgets")
    assert is_allowed("output_dir", allow) and is_allowed("progress", allow)
    assert is_allowed("wandb.enable", allow) and is_allowed("wandb.project", allow)
    assert is_allowed("inner.budgets.reach.patience", allow)
    assert not is_allowed("progress_bar", allow) and not is_allowed("inner.lr", allow)
    assert not is_allowed("output", allow) and not is_allowed("seed", allow)
    fp = settings_fingerprint(Outer(), allow)
    assert set(fp.settings) == {"seed", "skills", "inner.lr", "inner.mode", "inner.shape", "inner.tau",
                                "inner.features"}
    assert fp.sha256 == settings_digest(fp.settings) and fp.allow == allow


def test_digest_and_comparison_are_canonical():
    a = {"x": 1, "y": [1.0, 2], "z": float("nan")}
    b = {"z": float("nan"), "y": [1, 2.0], "x": 1.0}  # other order, integral floats, NaN
    assert settings_digest(a) == settings_digest(b) and diff_settings(a, b) == {}
    # Numbers compare as Python compares them: LeRobot declares `replace_final_stride_with_dilation: int = False`
    # and draccus reads the stored `false` back as 0.
    assert diff_settings({"x": True, "y": False}, {"x": 1, "y": 0}) == {}
    assert diff_settings({"x": True}, {"x": 2}) == {"x": (True, 2)}
    assert diff_settings({"x": "1"}, {"x": 1}) == {"x": ("1", 1)}  # a string is not a number
    assert diff_settings({"x": 0.1}, {"x": 0.10000000000000002}) == {"x": (0.1, 0.10000000000000002)}
    assert canonical_json({"b": 1.0, "a": [2.5, True]}) == '{"a":[2.5,1],"b":1}'


def test_diff_names_changed_added_and_removed_keys():
    stored = {"seed": 1, "policy.lr": 0.1, "old": "x"}
    current = {"seed": 2, "policy.lr": 0.1, "new": [1]}
    diffs = diff_settings(stored, current)
    assert diffs == {"seed": (1, 2), "old": ("x", ABSENT), "new": (ABSENT, [1])}
    assert list(diffs) == sorted(diffs)


def test_mismatch_error_is_one_line_naming_the_file_and_every_key():
    err = SettingsMismatchError(Path("/run/settings_fingerprint.json"),
                                {"policy.aggregator": ("nash", "mean_grad"), "seed": (1, 2),
                                 "added": (ABSENT, "a\nb"), "wake.budgets": ({"a": 1}, {})})
    text = str(err)
    assert isinstance(err, ValueError) and "\n" not in text
    assert text.startswith("/run/settings_fingerprint.json: cannot resume with different settings "
                           "(stored -> requested): ")
    for part in ('policy.aggregator: "nash" -> "mean_grad"', "seed: 1 -> 2", 'added: <absent> -> "a\\nb"',
                 'wake.budgets: {"a": 1} -> {}'):
        assert part in text
    assert err.path == Path("/run/settings_fingerprint.json") and set(err.diffs) == {
        "policy.aggregator", "seed", "added", "wake.budgets"}


def test_check_settings_ignores_stored_keys_that_are_allow_listed_now(tmp_path):
    current = settings_fingerprint(Outer(seed=5), ("output_dir", "progress", "wandb.*"))
    stored = flatten_settings(Outer(seed=5, progress=False, output_dir=Path("/elsewhere")))  # a legacy full config
    check_settings(tmp_path / "x.json", stored, current)
    stored["inner.lr"] = 0.5
    with pytest.raises(SettingsMismatchError, match=r"x.json: .*inner.lr: 0.5 -> 0.001 "):
        check_settings(tmp_path / "x.json", stored, current)


def test_fingerprint_file_round_trip_and_tampering_is_named(tmp_path):
    fp = settings_fingerprint(Outer(), ("output_dir",))
    path = write_fingerprint(tmp_path / FINGERPRINT_FILE, fp)
    data = json.loads(path.read_text())
    assert data["sha256"] == fp.sha256 and data["allow_list"] == ["output_dir"]
    assert "/abs/run" not in path.read_text()  # allow-listed values (where the run is) are not stored
    assert read_fingerprint(path) == fp.settings
    data["settings"]["seed"] = 2  # edited by hand: the sha256 no longer matches
    path.write_text(json.dumps(data))
    with pytest.raises(CorruptFileError, match=f"{FINGERPRINT_FILE}: the stored settings do not match their sha256"):
        read_fingerprint(path)
    path.write_text(json.dumps({**data, "format": "other"}))
    with pytest.raises(CorruptFileError, match="not a settings fingerprint"):
        read_fingerprint(path)
    path.write_text("{trunc")
    with pytest.raises(CorruptFileError, match="not valid JSON"):
        read_fingerprint(path)


def test_output_dir_of_a_run_config_is_its_directory():
    run_cfg = Path("/copies/run7/train_config.json")
    assert output_dir_for(run_cfg, ["--resume=true"], Path(".")) == Path("/copies/run7")
    assert output_dir_for(run_cfg, ["--output_dir=/x"], Path("/x")) == Path("/x")  # explicit wins
    assert output_dir_for(run_cfg, ["--output_dir", "."], Path(".")) == Path(".")
    assert output_dir_for(None, [], Path(".")) == Path(".")  # no config file: the working directory
    assert output_dir_for("configs/p.json", [], Path("outputs/p")) == Path("outputs/p")


def test_fingerprint_is_a_frozen_value():
    fp = settings_fingerprint({"a": 1})
    assert isinstance(fp, SettingsFingerprint) and fp == settings_fingerprint({"a": 1.0})
    with pytest.raises(AttributeError):
        fp.sha256 = "x"  # type: ignore[misc]


# -- helpers shared with the programs' resume-settings tests -------------------------------------------------------

def leaves(tree: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """(path, value) of every leaf of a nested JSON config, as :func:`flatten_settings` sees them."""
    if isinstance(tree, dict) and tree:
        for key, value in tree.items():
            yield from leaves(value, (*path, key))
    else:
        yield path, tree


def with_leaf(tree: dict[str, Any], path: tuple[str, ...], value: Any) -> dict[str, Any]:
    out = copy.deepcopy(tree)
    node = out
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return out


def changed_values(key: str, value: Any, choices: dict[str, list[Any]]) -> list[Any]:
    """Candidate other values of one setting, by type: flip a bool, +1 / -1 an int, x2 / +0.5 a float, the other
    valid choices of a string (``choices[key]``; a string setting without an entry is an error, so a new setting
    must be thought about), append to a list. ``choices[key]`` also gives the values of ``None`` settings."""
    if key in choices:
        return [c for c in choices[key] if canonical_json(c) != canonical_json(value)]
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value + 1, value - 1, 2 * value + 3]
    if isinstance(value, float):
        return [value * 2 if value else 1.0, value + 0.5, value / 2]
    if isinstance(value, list):
        extra = (max(value) + 1 if value else 1) if all(isinstance(v, int) for v in value) else "extra"
        return [[*value, extra]]
    raise AssertionError(f"{key} = {value!r}: no rule to change it; add its valid values to the test's CHOICES")


def tree_state(root: Path) -> str:
    """sha256 over every path under ``root`` with its bytes and modification time: equal means nothing was
    created, deleted, rewritten or touched."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        st = path.stat()
        h.update(f"{path.relative_to(root)}|{path.is_dir()}|{st.st_mtime_ns}|".encode())
        if path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()


def assert_refused_naming(check: Callable[[], Any], key: str) -> SettingsMismatchError:
    """``check()`` raises a one-line :class:`SettingsMismatchError` whose changes are ``key`` (or keys below it,
    e.g. a dict that gained an entry) with ``stored -> requested`` values."""
    with pytest.raises(SettingsMismatchError) as info:
        check()
    err = info.value
    text = str(err)
    assert "\n" not in text and str(err.path) in text
    assert key in err.diffs or any(k.startswith(f"{key}.") for k in err.diffs), (key, err.diffs)
    for k, (old, new) in err.diffs.items():
        assert f"{k}: " in text and " -> " in text
        if isinstance(old, float) and isinstance(new, float) and not (math.isnan(old) or math.isnan(new)):
            assert old != new
    return err


def test_an_empty_mapping_is_the_same_as_an_absent_key():
    # A run started before `method_options` existed resumes under code whose default is `{}`; a non-empty value
    # (a real option) still counts, as does an empty list or string (not "no values").
    assert diff_settings({"seed": 1}, {"seed": 1, "method_options": {}}) == {}
    assert diff_settings({"seed": 1, "method_options": {}}, {"seed": 1}) == {}
    assert diff_settings({"seed": 1}, {"seed": 1, "method_options": {"lam": 100}}) == {
        "method_options": (ABSENT, {"lam": 100})}
    assert diff_settings({"m": {}}, {"m": {"lam": 1}}) == {"m": ({}, {"lam": 1})}
    assert diff_settings({}, {"v": []}) == {"v": (ABSENT, [])}
    assert diff_settings({}, {"v": ""}) == {"v": (ABSENT, "")}


def test_derived_settings_are_fingerprinted_and_a_run_that_predates_them_still_matches(tmp_path):
    derived = {"method_config": {"lam": 1.0, "fisher_states": 2000}}
    current = settings_fingerprint(Outer(), ("output_dir",), derived)
    assert current.derived == ("method_config",)
    assert current.settings["method_config.lam"] == 1.0 and current.settings["seed"] == 1
    assert current.sha256 != settings_fingerprint(Outer(), ("output_dir",)).sha256
    write_fingerprint(tmp_path / FINGERPRINT_FILE, current)
    assert json.loads((tmp_path / FINGERPRINT_FILE).read_text())["derived"] == ["method_config"]
    check_settings(tmp_path / "x.json", read_fingerprint(tmp_path / FINGERPRINT_FILE), current)
    # a stored fingerprint written before the code derived the key: counts as equal there ...
    older = settings_fingerprint(Outer(), ("output_dir",)).settings
    check_settings(tmp_path / "x.json", older, current)
    # ... but a recorded value that differs (a changed default), and any other setting, still refuse
    changed = settings_fingerprint(Outer(), ("output_dir",), {"method_config": {"lam": 100.0, "fisher_states": 2000}})
    with pytest.raises(SettingsMismatchError, match=r"x.json: .*method_config.lam: 1.0 -> 100.0 "):
        check_settings(tmp_path / "x.json", current.settings, changed)
    with pytest.raises(SettingsMismatchError, match=r"seed: 2 -> 1 "):
        check_settings(tmp_path / "x.json", {**older, "seed": 2}, current)
    # the leniency is for derived keys only: a configuration key the stored run lacks refuses
    with pytest.raises(SettingsMismatchError, match=r"inner.lr: <absent> -> 0.001 "):
        check_settings(tmp_path / "x.json", {k: v for k, v in older.items() if k != "inner.lr"}, current)
    with pytest.raises(ValueError, match=r"derived settings \['seed'\] are also settings"):
        settings_fingerprint(Outer(), (), {"seed": 3})


def test_a_resume_under_another_library_version_is_refused_first_in_one_line(tmp_path):
    """``stack.*`` keys (library versions) are checked before every other setting: one line naming each library with
    both versions and the fingerprint's hint; equal versions pass; a run that recorded none counts as ``added``'s."""
    from sr_imitation.infra.fingerprint import StackMismatchError, check_stack, settings_fingerprint

    current = settings_fingerprint({"lr": 1.0}, derived={"stack": {"lerobot": "0.6.1"}},
                                   added={"stack.lerobot": "0.4.4"}, stack_hint="use tag v0")
    check_stack(tmp_path / "f.json", {"lr": 2.0, "stack.lerobot": "0.6.1"}, current)  # settings are not its business
    for stored, made in (({"lr": 2.0, "stack.lerobot": "0.6.0"}, "0.6.0"), ({"lr": 2.0}, "0.4.4")):
        with pytest.raises(StackMismatchError) as refused:
            check_stack(tmp_path / "f.json", stored, current)
        message = str(refused.value)
        assert message == (f"{tmp_path / 'f.json'}: this run was made with lerobot {made} and cannot resume under "
                           "lerobot 0.6.1 (another release computes other numbers): use tag v0")
