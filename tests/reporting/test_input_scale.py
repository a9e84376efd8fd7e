"""sr_imitation.reporting.input_scale: the state input weights' column norms at each checkpoint of a run. Under
``--stream.stats=seen`` a stream whose skills lie apart widens the statistics and re-expresses the weights exactly,
so the norms grow by about the factor the standard deviations grow; under ``union`` they stay where training leaves
them."""

from __future__ import annotations

import json

import pytest

from sr_imitation.reporting.input_scale import STATE_INPUT, main, stage_input_norms
from sr_imitation.substrates.act.evaluate import EvalConfig
from sr_imitation.substrates.act.trainer import ACTTrainer
from tests.substrates.act.helpers import make_skill_dataset, tiny_stream_config

SKILLS = ["approach", "place", "insert"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("apart")
    for i, skill in enumerate(SKILLS):
        make_skill_dataset(root, skill, i, image=False, offset=6.0 * i)
    out = {}
    for stats in ("seen", "union"):
        cfg = tiny_stream_config(root, tmp_path_factory.mktemp(stats), SKILLS, use_images=False, stats=stats)
        cfg.eval = EvalConfig(env="none", episodes=0)
        ACTTrainer(cfg).run()
        out[stats] = cfg.output_dir
    return out


def test_seen_rescales_the_state_input_weights_and_union_does_not(runs):
    seen, union = stage_input_norms(runs["seen"]), stage_input_norms(runs["union"])
    assert [(r["stage"], r["skill"], r["phase"]) for r in seen] == [
        (1, "approach", "wake"), (2, "place", "wake"), (2, "place", "sleep"), (3, "insert", "wake"),
        (3, "insert", "sleep")]
    for rows in (seen, union):
        assert all(r["max"] == max(r["column_norms"]) and r["column_norms"][r["argmax"]] == r["max"] for r in rows)
    # union: a few tiny wakes move the weights little; seen: the widening statistics multiply them
    assert max(r["max"] for r in union) < 2 * union[0]["max"]
    assert seen[-1]["max"] > 3 * seen[0]["max"] and seen[-1]["max"] > 3 * union[-1]["max"]


def test_the_command_writes_one_checked_file_and_a_missing_run_is_one_line(runs, tmp_path, capsys):
    from sr_imitation.infra.cli_errors import run_cli
    from sr_imitation.io import read_checked_json

    main([str(runs["seen"]), "--output", str(tmp_path / "scale.json")])
    stored = read_checked_json(tmp_path / "scale.json")
    assert stored["layer"] == STATE_INPUT and list(stored["runs"]) == [str(runs["seen"])]
    assert json.loads(json.dumps(stage_input_norms(runs["seen"]))) == stored["runs"][str(runs["seen"])]
    assert "| 3 | insert | sleep |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        run_cli("sr_imitation.reporting.input_scale", main, [str(tmp_path / "nowhere")])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nowhere: no stage folders" in err
