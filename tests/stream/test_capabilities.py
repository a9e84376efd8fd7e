"""Substrate capabilities: what a method asks of a substrate is declared, checked when the run is built, and reached
typed; every registered method runs on a substrate, and on every substrate its comparison restricts it to."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

import sr_imitation.substrates.sac  # noqa: F401  (registers CompoNet)
from sr_imitation.infra.fingerprint import settings_fingerprint
from sr_imitation.stream import METHODS, ContinualMethod, RunDirectory, StreamEngine
from sr_imitation.stream import capabilities as caps
from sr_imitation.stream.capabilities import (
    GaussianActor,
    PolicySnapshots,
    StoredDemonstrations,
    capability,
    missing_capabilities,
)
from sr_imitation.stream.methods.registry import refusal
from sr_imitation.substrates.act.substrate import ACTSubstrate
from sr_imitation.substrates.sac.substrate import SACSubstrate
from tests.stream.toy import ToySubstrate

SUBSTRATES = {"act": ACTSubstrate, "sac": SACSubstrate}
CAPABILITIES = {name: obj for name, obj in vars(caps).items() if inspect.isclass(obj)
                and getattr(obj, "_is_runtime_protocol", False) and obj is not caps.ChunkTeacher}


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_runs_on_a_substrate_and_on_each_one_it_is_restricted_to(name):
    cls = METHODS[name]
    assert any(refusal(cls, substrate) is None for substrate in SUBSTRATES.values()), name
    for substrate in sorted(set(cls.substrates or ()) & set(SUBSTRATES)):
        assert refusal(cls, SUBSTRATES[substrate]) is None, (name, substrate)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_capability_a_method_reaches_for_is_declared(name):
    """``capability(substrate, X)`` in a method's own code (and its parents') means X is in ``requires``."""
    cls = METHODS[name]
    used = set()
    for klass in cls.__mro__:
        if klass in (ContinualMethod, object):
            continue
        used |= set(re.findall(r"capability\(\w+, (\w+)\)", inspect.getsource(klass)))
    declared = {c.__name__ for entry in (*cls.requires, *cls.option_requires) for c in caps.alternatives(entry)}
    assert used <= declared, (name, used)


def test_capabilities_are_small_and_documented():
    assert len(CAPABILITIES) >= 8
    for name, protocol in CAPABILITIES.items():
        members = [m for m in vars(protocol) if not m.startswith("_")]
        assert 1 <= len(members) <= 3, (name, members)
        assert protocol.__doc__ and all(getattr(protocol, m).__doc__ for m in members), name


class NeedsActor(ContinualMethod):
    name = "needs_actor"
    requires = (GaussianActor, StoredDemonstrations, PolicySnapshots)  # the toy has a Gaussian actor only


def test_the_engine_refuses_a_substrate_without_a_required_capability_before_writing(tmp_path):
    out = tmp_path / "run"
    substrate = ToySubstrate(out, ["a", "b"])
    run = RunDirectory(out, settings_fingerprint({"m": 1}), "config.json", {"m": 1}, resume=False, overwrite=False)
    with pytest.raises(ValueError) as err:
        StreamEngine(substrate, NeedsActor(substrate.method_settings()), run, progress=False)
    message = str(err.value)
    assert "\n" not in message
    assert "'needs_actor' needs a substrate with StoredDemonstrations, PolicySnapshots" in message
    assert "toy substrate" in message
    assert not out.exists()


def test_capability_returns_the_substrate_typed_or_names_what_is_missing():
    substrate = ToySubstrate(Path("."), ["a"])
    assert capability(substrate, GaussianActor) is substrate
    with pytest.raises(TypeError, match=r"ToySubstrate does not provide PolicySnapshots \(chunk_policy, "
                                        r"frozen_policy, policy_weights\)"):
        capability(substrate, PolicySnapshots)
    assert missing_capabilities(ToySubstrate, [GaussianActor, PolicySnapshots]) == ["PolicySnapshots"]
    assert missing_capabilities(SACSubstrate, [GaussianActor]) == []
    assert missing_capabilities(ACTSubstrate, [GaussianActor]) == ["GaussianActor"]


def test_a_union_requirement_is_met_by_either_of_its_capabilities():
    either = GaussianActor | caps.ActorSnapshotMemory
    assert caps.alternatives(either) == (GaussianActor, caps.ActorSnapshotMemory)
    assert missing_capabilities(SACSubstrate, [either]) == missing_capabilities(ACTSubstrate, [either]) == []
    assert missing_capabilities(ToySubstrate, [PolicySnapshots | caps.ActorSnapshotMemory, GaussianActor]) == [
        "either PolicySnapshots or ActorSnapshotMemory"]


def test_the_capability_table_says_which_substrates_provide_each_capability():
    rows = re.findall(r"^:class:`(\w+)`\s+((?:act|sac)(?:, (?:act|sac))*)\s", caps.__doc__ or "", re.MULTILINE)
    assert {name for name, _ in rows} == set(CAPABILITIES)
    for name, substrates in rows:
        provided = {s for s, cls in SUBSTRATES.items() if not caps.missing_members(cls, CAPABILITIES[name])}
        assert provided == set(substrates.split(", ")), name
