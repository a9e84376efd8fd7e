"""docs/ARCHITECTURE.md's two recipes, done exactly as written, so that they cannot go stale: a method is one file
(``tests/stream/l2_anchor.py``) plus its test; a substrate is one folder (``sr_imitation/substrates/toy/``, whose
``__init__.py`` is the recipe's code block, written here into a temporary folder on the package's path; its code is
``tests/stream/toy.py``) plus its test, and no other file; both run by ``sr-train``. A substrate missing any member
of the protocol is refused in one line before anything is written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import sr_imitation.stream.methods as methods_package
import tests.stream.l2_anchor  # registers l2_anchor, as the methods package registers its files
from sr_imitation import cli
from sr_imitation.core.memory import OutputDistillationMemory
from sr_imitation.io import read_checked_json
from sr_imitation.stream import METHODS, RunDirectory, StreamEngine, make_method, methods_for
from sr_imitation.stream.capabilities import protocol_members
from sr_imitation.stream.methods.base import ContinualMethod
from sr_imitation.stream.run import StreamRun
from sr_imitation.stream.substrate import MethodSettings, Substrate, SubstrateProtocolError, check_substrate
from sr_imitation.substrates import discover
from sr_imitation.substrates.registry import SUBSTRATES
from tests.conftest import recipe_init, recipe_method
from tests.stream import toy
from tests.stream.conftest import KilledError
from tests.stream.toy import ToySubstrate

DOC = Path(__file__).resolve().parents[2] / "docs" / "ARCHITECTURE.md"


def _weights(result) -> list[torch.Tensor]:
    return result["weights"]


def _moved_since_wake(out: Path, k: int, result) -> float:
    """The squared distance of a finished run's final weights from its weights after wake ``k``."""
    substrate = ToySubstrate(out, ["a", "b", "c"])
    substrate.setup()
    return float(sum((w - a).pow(2).sum() for w, a in zip(_weights(result), substrate.parameters_at(k, "wake"),
                                                           strict=True)))


# -- adding a method ---------------------------------------------------------------------------------------------
def test_every_file_of_the_methods_package_registers_itself():
    """A method file needs no import elsewhere: the package imports each of its public modules."""
    registered = {cls.__module__.rsplit(".", 1)[-1] for cls in METHODS.values()}
    files = {p.stem for p in Path(methods_package.__file__).parent.glob("*.py")
             if not p.stem.startswith("_") and p.stem not in ("base", "registry")}
    assert files <= registered


def test_the_example_method_runs_on_any_substrate_through_sr_train_and_resumes_to_the_same_weights(tmp_path, sr_train,
                                                                                                  monkeypatch):
    assert "l2_anchor" in methods_for(ToySubstrate)  # nothing asked beyond the protocol: every substrate
    flags = ["--substrate=toy", "--stream.skills=[a,b,c]", "--progress=false"]
    l2 = tmp_path / "l2"
    anchored = sr_train([*flags, "--method=l2_anchor", "--method_options={lam: 10.0}", f"--output_dir={l2}"])
    plain = sr_train([*flags, "--method=sequential_bc", f"--output_dir={tmp_path / 'plain'}"])
    assert anchored["final_phases"] == ["wake"] * 3 and anchored["memories"] == []
    # the pull keeps the policy nearer the previous skill's weights than plain fine-tuning does
    assert _moved_since_wake(l2, 1, anchored) < _moved_since_wake(tmp_path / "plain", 1, plain)
    # its settings are fingerprinted with their defaults
    assert '"method_config.lam": 10.0' in (l2 / "settings_fingerprint.json").read_text()
    # killed after the second wake, resumed from the run's stored config: the same weights
    killed = tmp_path / "killed"
    real = ToySubstrate.evaluate

    def dying(self, k, phase, skills):
        if (k, phase) == (1, "wake.eval"):
            raise KilledError
        return real(self, k, phase, skills)

    monkeypatch.setattr(ToySubstrate, "evaluate", dying)
    with pytest.raises(KilledError):
        sr_train([*flags, "--method=l2_anchor", "--method_options={lam: 10.0}", f"--output_dir={killed}"])
    monkeypatch.setattr(ToySubstrate, "evaluate", real)
    resumed = sr_train([f"--config_path={killed / 'train_config.json'}", "--resume=true"])
    assert all(torch.equal(a, b) for a, b in zip(_weights(resumed), _weights(anchored), strict=True))


# -- adding a substrate --------------------------------------------------------------------------------------------
def test_the_toy_substrate_added_as_one_folder_runs_a_stream_with_sleep_through_sr_train(tmp_path, sr_train):
    known = sorted(discover())  # the registry: the package's own folders and the toy's
    assert "toy" in known and {"act", "sac"} <= set(known)
    choices = re.escape(str(known))
    with pytest.raises(ValueError, match=rf"^substrate: unknown substrate 'toyy'; choose from {choices}$"):
        cli.substrate_of(["--substrate=toyy"])  # the folder alone registered it, beside the package's own
    out = tmp_path / "run"
    result = sr_train(["--substrate=toy", "--method=sr", "--stream.skills=[a,b]", "--progress=false",
                       f"--output_dir={out}"])
    assert SUBSTRATES["toy"].__module__ == "sr_imitation.substrates.toy"
    assert result["final_phases"] == ["wake", "sleep"] and result["memories"] == ["a", "b"]
    assert (out / "stage1" / "sleep.safetensors").is_file() and not (out / "stage0" / "sleep.safetensors").exists()
    assert (out / "train_config.json").is_file() and (out / "settings_fingerprint.json").is_file()
    # the same run through StreamRun in Python, as toy.main builds it
    cfg = toy.parse(["--method=sr", "--stream.skills=[a,b]", "--progress=false", f"--output_dir={tmp_path / 'py'}"])
    same = StreamRun(cfg, ToySubstrate.from_config(cfg), fingerprint=toy.fingerprint(cfg),
                     stored_config=toy.stored_config(cfg)).run()
    assert all(torch.equal(a, b) for a, b in zip(_weights(same), _weights(result), strict=True))
    # a resume with another setting is refused naming it; the sleep's flags are the shared --sleep.*
    with pytest.raises(Exception, match=r"wake_steps"):
        sr_train([f"--config_path={out / 'train_config.json'}", "--resume=true", "--wake_steps=5"])
    off = sr_train(["--substrate=toy", "--sleep.enabled=false", "--stream.skills=[a,b]", "--progress=false",
                    f"--output_dir={tmp_path / 'off'}"])
    assert off["final_phases"] == ["wake", "wake"]


def test_the_toy_substrate_gets_every_method_it_provides_for_and_only_those():
    for name in methods_for(ToySubstrate):
        make_method(name, ToySubstrate, ToySubstrate(Path("."), ["a"]).method_settings())
    assert "lwf" not in methods_for(ToySubstrate)  # PolicySnapshots: the toy has no frozen copies


def _lacking(member: str) -> ToySubstrate:
    """A toy substrate without ``member`` (neither in its class, its base's members included, nor on the instance)."""
    namespace = {k: v for cls in reversed(ToySubstrate.__mro__[:-1]) for k, v in vars(cls).items()
                 if k not in (member, "__dict__", "__weakref__")}
    substrate = type("ToySubstrate", (), namespace)(Path("unused"), ["a", "b"])
    if member in vars(substrate):
        delattr(substrate, member)
    return substrate


@pytest.mark.parametrize("member", protocol_members(Substrate))
def test_a_substrate_lacking_any_protocol_member_is_refused_in_one_line_before_anything_is_written(tmp_path, member):
    out = tmp_path / "run"
    cfg = toy.parse(["--stream.skills=[a,b]", f"--output_dir={out}"])
    substrate = _lacking(member)
    with pytest.raises(TypeError) as err:
        StreamRun(cfg, substrate, fingerprint=toy.fingerprint(cfg), stored_config=toy.stored_config(cfg)).run()
    message = str(err.value)
    assert message == f"ToySubstrate is not a Substrate (sr_imitation.stream.substrate): it lacks {member}"
    run = RunDirectory(out, toy.fingerprint(cfg), "config.json", {}, resume=False, overwrite=False)
    with pytest.raises(TypeError, match=f"it lacks {member}$"):
        StreamEngine(substrate, METHODS["sr"](ToySubstrate(out, ["a"]).method_settings()), run, progress=False)
    assert not out.exists()


def test_every_missing_member_is_named_at_once_and_declared_values_are_checked(tmp_path):
    class Nearly:
        name = "nearly"

    with pytest.raises(TypeError, match=r"^Nearly is not a Substrate \(sr_imitation.stream.substrate\): it lacks "
                                        r"begin_phase, evaluate, extension_keys, .*wake_eval_skills, wake_hooks$"):
        StreamEngine(Nearly(), METHODS["sr"](ToySubstrate(tmp_path, ["a"]).method_settings()),  # type: ignore[arg-type]
                     RunDirectory(tmp_path / "r", toy.fingerprint(toy.parse([])), "c.json", {}, False, False))
    substrate = ToySubstrate(tmp_path / "r", ["a"])
    substrate.seed_scheme = "mine"  # type: ignore[misc]
    with pytest.raises(TypeError, match=r"ToySubstrate.seed_scheme: unknown scheme 'mine'; choose from"):
        StreamEngine(substrate, METHODS["sr"](substrate.method_settings()),
                     RunDirectory(tmp_path / "r", toy.fingerprint(toy.parse([])), "c.json", {}, False, False))
    assert not (tmp_path / "r").exists()


def test_the_recipes_name_every_protocol_member_and_the_files_they_cite():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "ARCHITECTURE.md").read_text()
    method = doc[doc.index("### Adding a method"):doc.index("### Adding a substrate")]
    substrate = doc[doc.index("### Adding a substrate"):doc.index("## The imitation substrate")]
    assert [m for m in protocol_members(Substrate) if f"`{m}" not in substrate] == []
    for cited in ("WakeHooks", "StreamRun", "RunConfig", "settings_fingerprint", "train_config.json",
                  "sr_imitation/substrates/<name>/", "register_substrate", "tests/test_architecture.py"):
        assert cited in substrate, cited
    assert 'module = "tests.stream.toy"' in recipe_init() and "sr_imitation/substrates/toy/" in (toy.__doc__ or "")
    example = Path(tests.stream.l2_anchor.__file__).read_text()
    assert recipe_method() == example  # the whole file, as the recipe shows it
    for line in ('name = "l2_anchor"', 'substrate.parameters_at(k - 1, "wake")', "0.5 * self.config.lam"):
        assert line in method and line in example, line
    for path in ("tests/stream/toy.py", "tests/stream/l2_anchor.py", "tests/stream/test_recipes.py",
                 "tests/stream/conftest.py"):
        assert path in doc and (Path(__file__).resolve().parents[2] / path).is_file(), path


# -- what a substrate could leave out silently (issue 61): each is one line, before the run records anything -------
def test_method_options_change_the_result_on_the_toy_substrate(tmp_path, sr_train):
    """The recipe's substrate passes --method_options through: a stronger pull keeps the weights closer to the
    previous skill's than a weak one (lam 10 against 0.1, by a wide factor; SGD at the toy's lr 0.05 is stable up
    to lam 40)."""
    flags = ["--substrate=toy", "--method=l2_anchor", "--stream.skills=[a,b,c]", "--progress=false"]
    moved = {}
    for lam in (0.1, 10.0):
        out = tmp_path / f"lam{lam:g}"
        result = sr_train([*flags, f"--method_options={{lam: {lam}}}", f"--output_dir={out}"])
        moved[lam] = _moved_since_wake(out, 1, result)
    assert moved[10.0] < 0.2 * moved[0.1], moved


def _toy_run(tmp_path, substrate_class, *flags, cfg_edit=None):
    out = tmp_path / "run"
    cfg = toy.parse(["--stream.skills=[a,b]", "--progress=false", f"--output_dir={out}", *flags])
    if cfg_edit is not None:
        cfg_edit(cfg)
    substrate = substrate_class(out, cfg.stream.skills)
    return out, StreamRun(cfg, substrate, fingerprint=toy.fingerprint(cfg), stored_config=toy.stored_config(cfg))


class ClaimsOptions(ToySubstrate):
    def method_settings(self):
        return MethodSettings(sleep=self.sleep, distill_weight=lambda k: self.gamma, options={"lam": 0.5})


class SkipsAdjust(ToySubstrate):
    def wake_update(self, k, memories, distill_weight, opt, hooks):
        x = torch.randn(32, 4)
        batch = hooks.batch({"obs": x, "y": x @ self.maps[k]})
        loss = hooks.loss((self.policy(batch["obs"]) - batch["y"]).pow(2).sum(1).mean())
        opt.zero_grad()
        loss.backward()
        opt.step()  # hooks.adjust() left out: a projection like A-GEM's would never happen
        return loss


class Adjusting(ContinualMethod):
    """A method that changes the wake's gradients (as A-GEM, PCGrad do), not registered: the engine runs it."""

    name = "adjusting"

    def adjust_gradients(self, step):
        return {"adjusted": 1.0}


class DropsFiles(ToySubstrate):
    def save_policy(self, k, phase, files):
        super().save_policy(k, phase, {})


class ForgetsToSave(ToySubstrate):
    def make_memory(self, k):
        return OutputDistillationMemory.from_snapshot(self.skills[k], self.policy_fn, {"x": torch.randn(64, 4)})


def test_the_method_options_go_from_the_run_config_to_the_method_whatever_the_substrate_says(tmp_path):
    """--method_options never pass through the substrate: the run's own options reach the method, whatever its
    ``method_settings()`` holds (none from the toy, others from ``ClaimsOptions``)."""
    for substrate_class in (ToySubstrate, ClaimsOptions):
        _, run = _toy_run(tmp_path / substrate_class.__name__, substrate_class, "--method=l2_anchor",
                          "--method_options={lam: 5}")
        assert run.method.config.lam == 5.0, substrate_class
    _, run = _toy_run(tmp_path / "none", ClaimsOptions, "--method=l2_anchor")
    assert run.method.config.lam == type(run.method).config.lam == 1.0  # its default: the run gave no options


def test_the_shared_settings_are_checked_for_every_substrate(tmp_path):
    def hand_set_seed(cfg):
        cfg.sleep.seed = 3  # as a config that never called check_shared_settings would let through

    with pytest.raises(ValueError, match=r"^sleep.seed: set per stage from --seed"):
        _toy_run(tmp_path, ToySubstrate, cfg_edit=hand_set_seed)
    assert not (tmp_path / "run").exists()


def test_a_declared_wake_hook_the_wake_does_not_call_is_one_line_before_the_wake_is_recorded(tmp_path):
    out = tmp_path / "run"
    substrate = SkipsAdjust(out, ["a", "b"])
    run = RunDirectory(out, toy.fingerprint(toy.parse([])), "config.json", {}, resume=False, overwrite=False)
    engine = StreamEngine(substrate, Adjusting(substrate.method_settings()), run, progress=False)
    with pytest.raises(SubstrateProtocolError, match=r"^SkipsAdjust.wake called the wake hooks \{'wake_batch': 30, "
                                                     r"'wake_loss': 30, 'adjust_gradients': 0\} times: a substrate "
                                                     r"calls every hook it declares"):
        engine.run()
    assert not (out / "progress.json").exists()  # the wake is not recorded


@pytest.mark.parametrize(("substrate", "message", "recorded"), [
    (DropsFiles, r"^DropsFiles.save_policy did not write \['wake_history.json'\] \(at .*stage0/wake."
                 r"wake_history.json\): a substrate writes every file the engine hands it$", None),
    (ForgetsToSave, r"^ForgetsToSave: the memory of stage 1 was made but not saved where "
                    r"load_memory\(k, name='memory'\) finds it", "1.wake"),
])
def test_what_a_substrate_leaves_out_silently_is_one_line_before_its_phase_is_recorded(tmp_path, substrate, message,
                                                                                       recorded):
    out, run = _toy_run(tmp_path, substrate, "--method=sr")
    with pytest.raises(SubstrateProtocolError, match=message) as err:
        run.run()
    assert "\n" not in str(err.value)
    done = read_checked_json(out / "progress.json")["completed"] if (out / "progress.json").exists() else {}
    assert list(done) == ([] if recorded is None else [recorded])  # the failing phase is not recorded


def test_members_of_the_wrong_kind_are_named_with_the_missing_ones(tmp_path):
    class Wrong(ToySubstrate):
        name = 3

        def save_policy(self, k, phase):  # the protocol's is (k, phase, files)
            pass

    with pytest.raises(SubstrateProtocolError) as err:
        check_substrate(Wrong(tmp_path, ["a"]))
    assert str(err.value) == ("Wrong.name must be a str, got int; Wrong.save_policy does not take the protocol's "
                              "arguments (k, phase, files)")
    assert isinstance(err.value, ValueError)  # a user error on the command line: one line, no traceback
