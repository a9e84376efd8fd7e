"""The stream engine on a toy substrate: the phases each method runs, the one sleep call's wiring, resume after a
kill at every point, the run directory's refusals, and the method registry."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch

from sr_imitation.infra.fingerprint import SettingsMismatchError, settings_fingerprint
from sr_imitation.io import CorruptFileError
from sr_imitation.stream import (
    METHODS,
    ContinualMethod,
    RunDirectory,
    StreamEngine,
    make_method,
    method_class,
    methods_for,
    register_method,
)
from tests.stream.conftest import SKILLS, KilledError, make_engine
from tests.stream.toy import ToySubstrate
from tests.stream.wiring import same, sleep_recorder


@pytest.fixture
def reference(tmp_path) -> dict[str, Any]:
    return make_engine(tmp_path / "reference").run()


def test_phases_per_method(tmp_path):
    expected = {
        "sr": [["wake", "memory", "wake.eval"], ["wake", "memory", "wake.eval", "sleep", "sleep.eval"],
               ["wake", "memory", "wake.eval", "sleep", "sleep.eval"]],
        "wake_only": [["wake", "memory", "wake.eval"]] * 3,
        "sequential_bc": [["wake", "wake.eval"]] * 3,
    }
    for method, phases in expected.items():
        engine = make_engine(tmp_path / method, method)
        assert [engine.phases(k) for k in range(3)] == phases
        result = engine.run()
        done = json.loads((tmp_path / method / "progress.json").read_text())["completed"]
        assert sorted(done) == sorted(f"{k + 1}.{p}" for k in range(3) for p in phases[k])
        assert result["final_phases"] == ["sleep" if "sleep" in p else "wake" for p in phases]
        assert result["memories"] == ([] if method == "sequential_bc" else SKILLS)
    # sr with sleep turned off by the substrate's configuration is the wake-only ablation
    assert make_engine(tmp_path / "off", "sr", sleep=False).phases(1) == expected["wake_only"][1]


def test_wake_eval_covers_what_the_substrate_asks(tmp_path):
    engine = make_engine(tmp_path / "r")
    engine.run()
    progress = json.loads((tmp_path / "r" / "progress.json").read_text())["completed"]
    assert list(progress["1.wake.eval"]["success"]) == ["a"]  # no sleep follows: the stage evaluation
    assert list(progress["2.wake.eval"]["success"]) == ["b"]  # toy: only the new skill before a sleep
    assert list(progress["3.sleep.eval"]["success"]) == SKILLS


def test_the_sleep_gets_the_previous_final_policy_as_anchor_and_earlier_wake_snapshots(tmp_path, monkeypatch):
    calls: list[dict[str, Any]] = []
    monkeypatch.setattr("sr_imitation.stream.substrate.sleep_consolidate", sleep_recorder(calls))
    engine = make_engine(tmp_path / "r")
    engine.run()
    sub = engine.substrate
    assert [c["skills"] for c in calls] == [["a", "b"], ["a", "b", "c"]]
    assert [c["kwargs"]["is_final_skill"] for c in calls] == [False, True]
    # stage 2 (k=1): anchor theta_1^wake (stage 1 did not sleep), gates from theta_1^wake; starts at theta_2^wake
    assert same(calls[0]["anchor"], sub.parameters_at(0, "wake"))
    assert len(calls[0]["wake_snapshots"]) == 1 and same(calls[0]["wake_snapshots"][0], sub.parameters_at(0, "wake"))
    assert same(calls[0]["start"], sub.parameters_at(1, "wake"))
    # stage 3: anchor theta_2^sleep, gates from theta_1^wake and theta_2^wake
    assert same(calls[1]["anchor"], sub.parameters_at(1, "sleep"))
    assert [len(s) for s in calls[1]["wake_snapshots"]] == [4, 4]
    assert same(calls[1]["wake_snapshots"][1], sub.parameters_at(1, "wake"))
    record = json.loads((tmp_path / "r" / "progress.json").read_text())["completed"]["3.sleep"]
    assert len(record["memory_losses_before"]) == 3 and len(record["memory_losses_after"]) == 3


def _all_phases(method: str = "sr") -> list[tuple[int, str]]:
    engine = make_engine(Path("/nonexistent"), method)
    return [(k, p) for k in range(3) for p in engine.phases(k)]


@pytest.mark.parametrize("method", ["sr", "sequential_bc"])
def test_a_kill_after_any_phase_or_inside_it_resumes_to_identical_results(tmp_path, method):
    reference = make_engine(tmp_path / "reference", method).run()
    points = _all_phases(method)[:-1]
    for n, point in enumerate(points):
        for inside in (False, True):
            out = tmp_path / f"kill{n}_{int(inside)}"
            if inside:  # killed inside the phase after `point`: its files may exist, it is not recorded
                nxt = _all_phases(method)[n + 1]
                real = StreamEngine._run_phase

                def killing(self, k, phase, nxt=nxt, real=real):
                    record = real(self, k, phase)
                    if (k, phase) == nxt:
                        raise KilledError
                    return record

                with pytest.MonkeyPatch.context() as mp:
                    mp.setattr(StreamEngine, "_run_phase", killing)
                    with pytest.raises(KilledError):
                        make_engine(out, method).run()
            else:
                def kill(k, phase, point=point):
                    if (k, phase) == point:
                        raise KilledError

                with pytest.raises(KilledError):
                    make_engine(out, method, after_phase=kill).run()
            resumed = make_engine(out, method, resume=True).run()
            assert resumed["evals"] == reference["evals"], (point, inside)
            assert all(torch.equal(a, b) for a, b in zip(resumed["weights"], reference["weights"], strict=True))


def test_run_directory_refuses_before_writing(tmp_path):
    out = tmp_path / "r"
    with pytest.raises(KilledError):
        make_engine(out, after_phase=lambda k, p: _raise() if (k, p) == (1, "wake") else None).run()
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(FileExistsError, match="--resume=true"):
        make_engine(out).run()
    with pytest.raises(SettingsMismatchError, match=r"wake_steps: 30 -> 31"):
        make_engine(out, resume=True, wake_steps=31).run()
    with pytest.raises(FileNotFoundError, match="holds no run"):
        make_engine(tmp_path / "empty", resume=True).run()
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # a progress file edited by hand (or a flipped byte) is refused naming it, and is left as it was
    progress = out / "progress.json"
    good = progress.read_bytes()
    progress.write_bytes(good.replace(b'"1.wake"', b'"2.wake"'))
    with pytest.raises(CorruptFileError, match=r"progress.json: contents do not match its sha256"):
        make_engine(out, resume=True).run()
    progress.write_bytes(good)
    # leftovers of an interrupted atomic write are removed on resume, never read
    (out / "stage1" / ".wake.safetensors.abc.tmp").write_bytes(b"torn")
    (out / ".sleep.x1").mkdir()
    make_engine(out, resume=True).run()
    assert not list(out.rglob(".*.tmp")) and not (out / ".sleep.x1").exists()


def _raise() -> None:
    raise KilledError


def test_a_method_runs_on_every_substrate_with_what_it_requires_and_the_registry_names_the_choices():
    """Methods are open to any substrate that provides what they ask; a comparison's restriction and a missing
    capability are refused in one line naming the methods that do run there."""
    toy = ToySubstrate(Path("."), SKILLS)
    assert {"sr", "wake_only", "sequential_bc", "ewc", "der", "clear"} <= set(methods_for(ToySubstrate))
    assert methods_for(toy) == methods_for(ToySubstrate)
    assert "lwf" in METHODS and "lwf" not in methods_for(toy)  # the toy has no PolicySnapshots
    with pytest.raises(ValueError, match=r"^method: 'lwf' needs a substrate with PolicySnapshots "
                                         r"\(sr_imitation.stream.capabilities\); the toy substrate does not provide "
                                         r"it; choose from \[.*'sr'.*\]$"):
        make_method("lwf", toy, toy.method_settings())
    with pytest.raises(ValueError, match=r"^method: 'agem' is compared on the sac substrate only, not on toy"):
        make_method("agem", toy, toy.method_settings())
    with pytest.raises(ValueError, match=r"^method: unknown method 'no_such'; choose from \['agem', "):
        make_method("no_such", toy, toy.method_settings())
    with pytest.raises(ValueError, match=r"^method: 'agem' is compared on the sac substrate only"):
        method_class("agem", "toy")  # what a configuration checks before the substrate exists
    assert method_class("der", "toy") is METHODS["der"]
    with pytest.raises(TypeError, match="must set name"):
        register_method(type("Nameless", (ContinualMethod,), {}))
    with pytest.raises(ValueError, match="registered twice"):
        register_method(type("Impostor", (ContinualMethod,), {"name": "sr"}))


def test_a_new_method_is_one_class(tmp_path):
    """A method that keeps memories, never distils during wake and sleeps only after the last skill."""

    class SleepAtTheEnd(ContinualMethod):
        name = "sleep_at_the_end"
        stores_memories = True

        def sleeps_after(self, skill_number: int) -> bool:
            return skill_number == 3

    register_method(SleepAtTheEnd)
    try:
        engine = make_engine(tmp_path / "r", "sleep_at_the_end")
        result = engine.run()
        assert result["final_phases"] == ["wake", "wake", "sleep"]
        assert ("sleep", 2) in engine.substrate.calls and ("sleep", 1) not in engine.substrate.calls
    finally:
        METHODS.pop("sleep_at_the_end")


def test_a_method_needing_a_wake_hook_the_substrate_does_not_call_is_refused(tmp_path, monkeypatch):
    class BatchMixer(ContinualMethod):
        name = "batch_mixer"

        def wake_batch(self, step):
            return step.batch

    register_method(BatchMixer)
    try:
        assert BatchMixer(ToySubstrate(tmp_path, SKILLS).method_settings()).wake_hooks_used() == {"wake_batch"}
        make_engine(tmp_path / "ok", "batch_mixer")  # the toy substrate calls wake_batch
        monkeypatch.setattr(ToySubstrate, "wake_hooks", frozenset({"wake_loss", "adjust_gradients"}))  # no batch hook
        with pytest.raises(ValueError, match=r"needs the wake hooks \['wake_batch'\]; the toy substrate's wake"):
            make_engine(tmp_path / "refused", "batch_mixer")
    finally:
        METHODS.pop("batch_mixer")


def test_the_run_log_has_every_phase_and_sleep_iteration_and_survives_a_resume(tmp_path, caplog):
    from sr_imitation.infra.runlog import read_log

    out = tmp_path / "r"
    with pytest.raises(KilledError):
        make_engine(out, after_phase=lambda k, p: _raise() if (k, p) == (1, "sleep") else None).run()
    with caplog.at_level("INFO", logger="sr_imitation.stream.engine"):
        make_engine(out, resume=True).run()
    resumed = [r.getMessage() for r in caplog.records if r.getMessage().startswith("resuming")]
    assert resumed == ["resuming at stage 2 (b) sleep.eval, from the policy of stage 2 sleep"]  # names where it goes on
    records = read_log(out / "log.jsonl")
    phases = [(r["stage"], r["phase"]) for r in records if r["kind"] == "phase"]
    assert phases == [(k + 1, p) for k in range(3) for p in make_engine(tmp_path / "x").phases(k)]
    sleeps = [r for r in records if r["kind"] == "sleep"]
    assert {r["stage"] for r in sleeps} == {2, 3} and all(len(r["alpha"]) == r["stage"] for r in sleeps)
    assert all(r["solver_status"] in ("optimal", "closed_form", "pareto_stationary") for r in sleeps)
    evals = [r for r in records if r["kind"] == "phase" and r["phase"] == "sleep.eval"]
    assert set(evals[-1]) >= {"success.a", "success.b", "success.c", "seconds"}


def test_wandb_offline_mirrors_the_log_without_network(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from sr_imitation.infra.runlog import WandbConfig

    monkeypatch.setenv("WANDB_SILENT", "true")
    substrate = ToySubstrate(tmp_path / "r", SKILLS[:2])
    config = {"method": "sr"}
    run = RunDirectory(tmp_path / "r", settings_fingerprint(config), "config.json", config, False, False)
    engine = StreamEngine(substrate, make_method("sr", substrate, substrate.method_settings()), run, progress=False,
                          wandb=WandbConfig(enable=True, mode="offline"), log_config=config)
    engine.run()
    runs = list((tmp_path / "r" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and any(runs[0].rglob("*.wandb"))


def test_extending_a_finished_stream_equals_having_had_all_skills_from_the_start(tmp_path):
    """With the final-skill anchor rule made irrelevant (anchor also after the final skill), extending a finished
    2-skill run with a third skill is bit-identical to a 3-skill run. With the default rule it is not: the source's
    stage-2 sleep ran as a final sleep, without anchor (the paper's MT8 continues from MT5 the same way)."""
    full = make_engine(tmp_path / "full", anchor_after_final=True).run()
    make_engine(tmp_path / "first2", skills=SKILLS[:2], anchor_after_final=True).run()
    extended = make_engine(tmp_path / "extended", extend_from=tmp_path / "first2", anchor_after_final=True).run()
    assert extended["evals"] == full["evals"]
    assert all(torch.equal(a, b) for a, b in zip(extended["weights"], full["weights"], strict=True))
    redone = list(ToySubstrate(tmp_path, SKILLS).calls)
    assert redone == []  # (sanity: a fresh substrate has no calls)
    make_engine(tmp_path / "first2_default", skills=SKILLS[:2]).run()
    default = make_engine(tmp_path / "ext_default", extend_from=tmp_path / "first2_default").run()
    reference = make_engine(tmp_path / "full_default").run()
    assert not all(torch.equal(a, b) for a, b in zip(default["weights"], reference["weights"], strict=True))


def test_extension_runs_only_the_new_stages_and_refuses_mismatches_before_writing(tmp_path):
    source = tmp_path / "first2"
    make_engine(source, skills=SKILLS[:2]).run()
    engine = make_engine(tmp_path / "ext", extend_from=source)
    engine.run()
    assert {k for _, k in engine.substrate.calls} == {2}  # stages 1-2 imported, not re-run
    for kwargs, match in [
        ({"wake_steps": 31}, r"wake_steps: 30 -> 31"),
        ({"skills": ["b", "a", "c"]}, r"are not the first skills"),
        ({"skills": SKILLS[:2]}, r"are not the first skills"),
    ]:
        out = tmp_path / f"bad{len(list(tmp_path.iterdir()))}"
        with pytest.raises(ValueError, match=match):
            make_engine(out, extend_from=source, **kwargs).run()
        assert not out.exists()
    killed = tmp_path / "killed_source"
    with pytest.raises(KilledError):
        make_engine(killed, skills=SKILLS[:2], after_phase=lambda k, p: _raise() if (k, p) == (1, "sleep") else None
                    ).run()
    with pytest.raises(ValueError, match="not a finished run"):
        make_engine(tmp_path / "from_killed", extend_from=killed).run()
