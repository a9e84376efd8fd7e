"""SubstrateBase: what it provides and what a substrate writes itself (as docs/ARCHITECTURE.md's recipe lists them),
the protocol check on a substrate built on it, and the file layouts of the three substrates on it."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

from sr_imitation.stream.capabilities import protocol_members
from sr_imitation.stream.substrate import Substrate, SubstrateProtocolError, check_substrate
from sr_imitation.stream.substrate_base import SUBSTRATE_WRITES, CheckpointedPolicy, SubstrateBase
from tests.stream.toy import ToySubstrate

DOC = Path(__file__).resolve().parents[2] / "docs" / "ARCHITECTURE.md"
_ABSENT = object()


def _provided() -> set[str]:
    """The protocol's members SubstrateBase has."""
    return {m for m in protocol_members(Substrate) if inspect.getattr_static(SubstrateBase, m, _ABSENT) is not _ABSENT}


def test_a_substrate_writes_the_protocol_less_what_the_base_provides_and_names_its_policy():
    writes = (set(protocol_members(Substrate)) - _provided()) | set(protocol_members(CheckpointedPolicy))
    assert sorted(SUBSTRATE_WRITES) == sorted(writes)
    assert {"save_policy", "load_policy", "policy_file", "parameters_at", "save_memory", "load_memory",
            "import_stages", "source_skills"} <= _provided()


def test_the_recipe_lists_the_members_a_substrate_writes_and_those_the_base_provides():
    doc = DOC.read_text()
    recipe = " ".join(doc[doc.index("### Adding a substrate"):doc.index("## The imitation substrate")].split())
    writes = recipe[recipe.index("**The members the substrate writes itself**"):
                    recipe.index("**What `SubstrateBase` provides**")]
    provides = recipe[recipe.index("**What `SubstrateBase` provides**"):recipe.index("Every file read back")]
    named = set(re.findall(r"`(\w+)", writes))
    assert [m for m in SUBSTRATE_WRITES if m not in named] == []
    assert sorted(_provided() & named) == []  # what the base provides is not listed as the substrate's to write
    assert [m for m in sorted(_provided()) if f"`{m}" not in provides] == []


def test_a_substrate_on_the_base_is_told_every_member_it_still_lacks_in_one_line(tmp_path):
    class Bare(SubstrateBase):
        name = "bare"

    with pytest.raises(SubstrateProtocolError) as err:
        check_substrate(Bare())
    lacking = [m for m in sorted(SUBSTRATE_WRITES) if m != "name"]
    assert str(err.value) == f"Bare is not a Substrate (sr_imitation.stream.substrate): it lacks {', '.join(lacking)}"
    check_substrate(ToySubstrate(tmp_path, ["a"]))  # the toy is complete


def test_the_toy_keeps_its_files_where_they_were(tmp_path):
    toy = ToySubstrate(tmp_path, ["a", "b"])
    assert toy.checkpoint_path(1, "sleep") == tmp_path / "stage1" / "sleep.safetensors"
    assert toy.policy_file(0, "wake", "wake_history.json") == tmp_path / "stage0" / "wake.wake_history.json"
    assert toy.memory_path(1) == tmp_path / "memories" / "1.safetensors"
    assert toy.memory_path(0, "ewc") == tmp_path / "memories" / "0.ewc.safetensors"


def test_sac_keeps_its_files_where_they_were():
    from sr_imitation.substrates.sac.config import RLTrainConfig
    from sr_imitation.substrates.sac.substrate import SACSubstrate

    out = Path("/run")
    sac = SACSubstrate(RLTrainConfig(output_dir=out))
    assert sac.skills[:2] == ["reach-v3", "door-open-v3"]  # MT5's first two
    stage = out / "stages" / "02_door-open"
    assert sac.stage_dir(1) == stage and sac.memory_path(1) == stage / "memory.safetensors"
    assert sac.memory_path(1, "ewc") == stage / "ewc.safetensors"
    assert sac.checkpoint_path(1, "sleep") == stage / "sleep" / "agent.safetensors"
    assert sac.policy_file(1, "sleep", "sleep_diagnostics.json") == stage / "sleep" / "sleep_diagnostics.json"


def test_act_keeps_its_files_where_they_were():
    from sr_imitation.substrates.act.config import TrainStreamConfig
    from sr_imitation.substrates.act.substrate import ACTSubstrate

    out = Path("/run")
    act = ACTSubstrate(TrainStreamConfig(output_dir=out, method="sequential_bc"))
    first, second = out / f"skill_1_{act.skills[0]}", f"skill_2_{act.skills[1]}"
    assert act.stage_dir(0) == first and act.checkpoint_dir(0, "sleep") == first / "sleep"
    assert act.checkpoint_path(0, "wake") == first / "wake" / "pretrained_model" / "model.safetensors"
    assert act.policy_file(0, "wake", "wake_history.json") == first / "wake" / "wake_history.json"
    assert act.memory_path(1) == out / "memories" / f"{second}.safetensors"
    assert act.memory_path(1, "ewc") == out / "memories" / f"{second}.ewc.safetensors"
    assert act.run_files == ("stream_stats.safetensors",)
