"""The pre-registered paired tests (sr_imitation.reporting.stats) against SciPy, over families of inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import special
from scipy import stats as scipy_stats

from sr_imitation.reporting.stats import betainc, paired_test, t_sf


@pytest.mark.parametrize("a, b", [(0.5, 0.5), (2.0, 0.5), (0.5, 3.0), (10.0, 0.5), (1.5, 1.5)])
def test_betainc_matches_scipy_over_x(a, b):
    for x in np.linspace(0, 1, 41):
        assert betainc(a, b, float(x)) == pytest.approx(special.betainc(a, b, x), rel=1e-10, abs=1e-13)


@pytest.mark.parametrize("df", [1, 2, 4, 9, 30])
def test_t_survival_function_matches_scipy(df):
    for t in [-50, -3.2, -1, -0.1, 0, 0.1, 0.7, 1, 2.776, 5, 50]:
        assert t_sf(t, df) == pytest.approx(scipy_stats.t.sf(t, df), rel=1e-9, abs=1e-14)
    assert t_sf(math.inf, df) == 0 and t_sf(-math.inf, df) == 1


@pytest.mark.parametrize("seed", range(6))
def test_paired_test_matches_scipy_ttest_rel_and_is_invariant(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 9))
    a, b = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    for alternative in ("greater", "less", "two-sided"):
        ours = paired_test(a, b, alternative)
        ref = scipy_stats.ttest_rel(a, b, alternative=alternative)
        assert ours.t == pytest.approx(ref.statistic, rel=1e-12)
        assert ours.p == pytest.approx(ref.pvalue, rel=1e-9)
        assert ours.ci_low <= ours.mean <= ours.ci_high
    # adding the same value to both methods changes nothing; scaling both scales mean and CI, not t or p
    assert paired_test(a + 3, b + 3).p == pytest.approx(paired_test(a, b).p)
    scaled, base = paired_test(2 * a, 2 * b), paired_test(a, b)
    assert scaled.t == pytest.approx(base.t) and scaled.mean == pytest.approx(2 * base.mean)
    assert scaled.ci_high == pytest.approx(2 * base.ci_high)


def test_edge_cases():
    same = paired_test([0.5, 0.7, 0.9], [0.5, 0.7, 0.9], "greater")
    assert math.isnan(same.t) and same.p == 1.0 and same.mean == 0.0
    constant = paired_test([0.6, 0.8, 1.0], [0.5, 0.7, 0.9], "greater")  # every seed +0.1
    assert constant.t == math.inf and constant.p == 0.0
    assert paired_test([0.6, 0.8, 1.0], [0.5, 0.7, 0.9], "less").p == 1.0
    assert math.isnan(paired_test([1.0], [0.0]).p)
    with pytest.raises(ValueError, match="equal lengths"):
        paired_test([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="alternative"):
        paired_test([1.0, 2.0], [1.0, 0.0], "bigger")


def test_holm_adjustment_known_values_and_properties():
    from sr_imitation.reporting.stats import holm

    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])  # 4x, 3x, 2x then monotone
    assert holm([0.2]) == [0.2] and holm([]) == []
    assert holm([0.6, 0.7]) == [1.0, 1.0]  # capped
    nan = float("nan")
    out = holm([0.01, nan, 0.02])  # a test without data neither counts nor changes
    assert out[0] == pytest.approx(0.02) and np.isnan(out[1]) and out[2] == pytest.approx(0.02)
    rng = np.random.default_rng(0)
    for _ in range(50):
        raw = rng.uniform(0, 0.2, size=int(rng.integers(1, 8))).tolist()
        adj = holm(raw)
        assert all(a >= r - 1e-15 for a, r in zip(adj, raw, strict=True))  # never below the raw p
        order = np.argsort(raw)
        assert all(np.diff(np.asarray(adj)[order]) >= -1e-15)  # same order as the raw p
        assert min(adj) == pytest.approx(min(1.0, len(raw) * min(raw)))  # the smallest: Bonferroni


def test_the_hypotheses_command_pairs_archived_runs_by_seed(tmp_path, capsys):
    import json

    from scipy import stats as st

    from sr_imitation.experiments.hypotheses import HypothesesConfig, main
    from sr_imitation.io import write_checked_json
    from tests.reporting.test_results import _results

    shifts = {"sr": [0.0, -0.05, -0.02, -0.03], "wake_only": [-0.1, -0.06, -0.14]}  # wake_only has no seed 3
    for variant, values in shifts.items():
        for seed, shift in enumerate(values):
            run = tmp_path / f"{variant}_seed{seed}"
            run.mkdir()
            write_checked_json(run / "results.json", _results(seed=seed, shift=shift, sleep=variant == "sr"))
    main([f"--archive={tmp_path}", "--tests=[sr>wake_only]", f"--output={tmp_path / 'h'}"])
    row = json.loads((tmp_path / "h" / "hypotheses.json").read_text())["tests"][0]
    assert row["seeds"] == [0, 1, 2] and row["alternative"] == "greater"
    ref = st.ttest_rel(row["a_values"], row["b_values"], alternative="greater")
    assert row["p"] == pytest.approx(ref.pvalue) and row["mean"] == pytest.approx(np.mean([0.1, 0.01, 0.12]))
    assert "sr>wake_only (greater)" in capsys.readouterr().out
    assert (tmp_path / "h" / "hypotheses.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the paired-seeds figure
    main([f"--archive={tmp_path}", "--tests=[sr>wake_only,sr!=wake_only]", "--holm=true", f"--output={tmp_path / 'h'}"])
    one, two = json.loads((tmp_path / "h" / "hypotheses.json").read_text())["tests"]
    assert one["p_holm"] == pytest.approx(min(1.0, max(2 * min(one["p"], two["p"]), one["p"])))
    assert "Holm p" in capsys.readouterr().out
    with pytest.raises(ValueError, match="not of the form"):
        HypothesesConfig(tests=["sr=wake_only"])
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        HypothesesConfig(archive=tmp_path / "typo")


def test_runs_without_evaluation_are_tested_on_their_final_validation_l1(tmp_path, capsys, caplog):
    """--eval.env=none (no simulator): no success rate, so "sleep helps" is sr<wake_only on the mean validation l1
    over skills under the final policy (``losses.validation_l1``'s last row); asking for AFSR names the way out."""
    import json
    import logging

    from sr_imitation.experiments.hypotheses import HypothesesConfig, main
    from sr_imitation.io import write_checked_json
    from tests.reporting.test_results import _results

    last_rows = {"sr": [[0.30, 0.20, 0.10], [0.28, 0.22, 0.12]], "wake_only": [[0.45, 0.30, 0.10], [0.40, 0.35, 0.11]]}
    for variant, rows in last_rows.items():
        for seed, last in enumerate(rows):
            l1 = [[0.1, None, None], [0.2, 0.1, None], last]
            losses = {"validation_l1": l1, "memory_loss": [[0.0, None, None], [0.01, 0.0, None], [0.02, 0.01, None]]}
            run = tmp_path / f"{variant}_seed{seed}"
            run.mkdir()
            write_checked_json(run / "results.json", _results(seed=seed, sleep=variant == "sr", success=None,
                                                              after_wake=None, spi=None, evaluation="none",
                                                              losses=losses))
    main([f"--archive={tmp_path}", "--tests=[sr<wake_only]", "--metric=val_l1", f"--output={tmp_path / 'h'}"])
    row = json.loads((tmp_path / "h" / "hypotheses.json").read_text())["tests"][0]
    assert row["a_values"] == pytest.approx([0.2, 0.2066667])
    assert row["b_values"] == pytest.approx([0.2833333, 0.2866667])
    assert row["alternative"] == "less" and row["mean"] == pytest.approx(-0.0816667) and row["seeds"] == [0, 1]
    with caplog.at_level(logging.WARNING):
        main([f"--archive={tmp_path}", "--tests=[sr>wake_only]"])
    assert "none measured afsr (--metric=val_l1 for runs without evaluation)" in caplog.text
    with pytest.raises(ValueError, match="val_l1"):
        HypothesesConfig(archive=tmp_path, metric="l1")


def test_a_flag_value_the_shell_cut_short_is_one_line_naming_the_value(tmp_path, capsys):
    """``--tests=[sr>wake_only]`` unquoted: the shell redirects at ``>`` and draccus gets ``[sr``."""
    from sr_imitation.experiments.hypotheses import main
    from sr_imitation.infra.cli_errors import run_cli

    with pytest.raises(SystemExit) as stop:
        run_cli("hypotheses", main, [f"--archive={tmp_path}", "--tests=[sr"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not valid YAML: '[sr'" in err and "quote" in err



def test_a_family_s_figure_shows_its_holm_verdict(tmp_path):
    """With --holm the panel titles carry the adjusted p's and the family's verdict (the one a test is judged by),
    so the figure cannot be read as if the unadjusted p decided; without it they do not."""
    from sr_imitation.experiments.hypotheses import HypothesesConfig, panel_title, run_tests

    _archive(tmp_path, {"sr": [0.7, 0.6, 0.65, 0.68], "wake_only": [0.5, 0.55, 0.4, 0.6],
                        "replay": [0.7, 0.6, 0.6, 0.66]})
    family = run_tests(HypothesesConfig(archive=tmp_path, tests=["sr>wake_only", "sr!=replay"], holm=True))
    for r in family:
        verdict = "rejected" if r["significant_holm"] else "not rejected"
        assert panel_title("t", r).splitlines()[-1] == \
            f"Holm: p = {r['p_holm']:.4f}, sign-flip {r['sign_flip_p_holm']:.4f}: {verdict}"
    alone = run_tests(HypothesesConfig(archive=tmp_path, tests=["sr>wake_only"]))[0]
    assert len(panel_title("t", alone).splitlines()) == 2 and "Holm" not in panel_title("t", alone)


def test_a_p_below_1e_4_is_printed_as_a_number_not_as_zero(tmp_path):
    """The table and the figure print p with 4 decimals, and below 1e-4 in scientific notation: G1's p = 1.3e-05 was
    drawn as "p = 0.0000"."""
    from sr_imitation.experiments.hypotheses import HypothesesConfig, format_p, panel_title, render, run_tests

    assert [format_p(p) for p in (0.5, 0.03125, 1e-4, 9.9e-5, 1.2836957924526441e-05)] == \
        ["0.5000", "0.0312", "0.0001", "9.9e-05", "1.3e-05"]
    _archive(tmp_path, {"sr": [0.7, 0.69, 0.7, 0.695, 0.7], "wake_only": [0.5, 0.495, 0.505, 0.5, 0.49]})
    (r,) = run_tests(HypothesesConfig(archive=tmp_path, tests=["sr>wake_only"]))
    assert r["p"] < 1e-4
    table = render([r], tmp_path)
    assert f"| {format_p(r['p'])} | 0.0312 |" in table and "0.0000" not in table
    assert f"p = {format_p(r['p'])}, sign-flip 0.0312" in panel_title("t", r)


def test_a_note_is_kept_as_typed(tmp_path, capsys):
    """``--note`` is free text: "M1 and M2: the family" reached hypotheses.md as the YAML mapping draccus read from
    it (``{'M1 and M2': 'the family'}``); text fields now hold what was typed, whatever YAML makes of it."""
    from sr_imitation.experiments.hypotheses import main

    _archive(tmp_path, {"sr": [0.7, 0.6, 0.65], "wake_only": [0.5, 0.55, 0.4]})
    for note in ("M1 and M2: the family, Holm over both", "[a list, or not]", "ends with a colon:", "#1 # two",
                 "#1", "!important", "- a dash", "*starred*", "> quoted"):
        main([f"--archive={tmp_path}", "--tests=[sr>wake_only]", f"--note={note}", f"--output={tmp_path / 'h'}"])
        assert f"\n\n{note}\n\n" in (tmp_path / "h" / "hypotheses.md").read_text()
    main([f"--archive={tmp_path}", "--tests=[sr>wake_only]", "--note", "as: two tokens", f"--output={tmp_path / 'h'}"])
    assert "\n\nas: two tokens\n\n" in (tmp_path / "h" / "hypotheses.md").read_text()
    main([f"--archive={tmp_path}", "--tests=[sr>wake_only]", """--note='quoted: by the user'""",
          f"--output={tmp_path / 'h'}"])
    assert "\n\nquoted: by the user\n\n" in (tmp_path / "h" / "hypotheses.md").read_text()


def test_the_sign_flip_p_is_the_exact_fraction_of_sign_assignments():
    import itertools

    from sr_imitation.reporting.stats import sign_flip_p

    rng = np.random.default_rng(3)
    for n in (1, 3, 5, 8):
        d = rng.normal(0.05, 0.1, size=n)
        brute = [np.mean(np.array(s) * np.abs(d)) for s in itertools.product((-1, 1), repeat=n)]
        assert sign_flip_p(d, "greater") == pytest.approx(np.mean([m >= d.mean() - 1e-12 for m in brute]))
        assert sign_flip_p(d, "less") == pytest.approx(np.mean([m <= d.mean() + 1e-12 for m in brute]))
        assert sign_flip_p(d, "two-sided") == pytest.approx(np.mean([abs(m) >= abs(d.mean()) - 1e-12 for m in brute]))
    assert sign_flip_p([0.1] * 5, "greater") == 1 / 32  # every pair positive: the floor 2^-n
    assert sign_flip_p([0.1] * 10, "greater") == 1 / 1024
    assert sign_flip_p([0.1] * 5, "two-sided") == 2 / 32
    assert sign_flip_p([0.0, 0.0, 0.0], "greater") == 1.0  # no evidence either way
    assert sign_flip_p(-np.array([0.3, 0.1, 0.2]), "greater") == 1.0
    assert sign_flip_p([0.2, -0.1, 0.3], "greater") == sign_flip_p([-0.2, 0.1, -0.3], "less")  # mirror symmetry
    with pytest.raises(ValueError, match="exact enumeration stops at 20"):
        sign_flip_p(np.ones(21))


def test_a_family_spans_archives_and_labels_are_exploratory_unless_pre_registered(tmp_path):
    from sr_imitation.experiments.hypotheses import HypothesesConfig, render, run_tests
    from sr_imitation.reporting.stats import holm

    first, second = tmp_path / "one", tmp_path / "two"
    _archive(first, {"sr": [0.7, 0.6, 0.65], "wake_only": [0.5, 0.55, 0.4]})
    _archive(second, {"sr": [0.3, 0.4, 0.35, 0.5], "wake_only": [0.3, 0.2, 0.4, 0.4]})
    cfg = HypothesesConfig(archive=first, tests=["sr>wake_only", f"{second}::sr>wake_only"], holm=True)
    rows = run_tests(cfg)
    assert [r["archive"] for r in rows] == [str(first), str(second)] and [r["n"] for r in rows] == [3, 4]
    assert rows[1]["a_values"] == pytest.approx([0.3, 0.4, 0.35, 0.5])
    assert rows[0]["sign_flip_p"] == 1 / 8  # all three pairs positive
    assert [r["sign_flip_p_holm"] for r in rows] == holm([r["sign_flip_p"] for r in rows])
    text = render(rows, first)
    assert text.startswith("Exploratory (not pre-registered) paired tests") and "sign-flip p" in text
    assert render(rows, first, preregistered=True).startswith("Pre-registered paired tests")
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        HypothesesConfig(archive=first, tests=[f"{tmp_path / 'nowhere'}::sr>wake_only"])


def test_a_test_pairs_one_variant_across_two_archives_by_training_seed(tmp_path):
    """``<folder>::sr!=<other>::sr``: the same variant under two settings, paired by seed (only common seeds)."""
    from sr_imitation.experiments.hypotheses import HypothesesConfig, main, render, run_tests

    seen, union = tmp_path / "seen", tmp_path / "union"
    _archive(seen, {"sr": [0.7, 0.6, 0.65], "wake_only": [0.4, 0.5, 0.45]})
    _archive(union, {"sr": [0.5, 0.55, 0.6, 0.7], "wake_only": [0.4, 0.3, 0.5, 0.2]})
    tests = [f"{seen}::sr!={union}::sr", f"{seen}::wake_only<{union}::wake_only", f"{seen}::sr>wake_only"]
    rows = run_tests(HypothesesConfig(archive=union, tests=tests))
    assert [r["seeds"] for r in rows] == [[0, 1, 2], [0, 1, 2], [0, 1, 2]]  # union's seed 3 has no partner
    assert rows[0]["a_values"] == pytest.approx([0.7, 0.6, 0.65])
    assert rows[0]["b_values"] == pytest.approx([0.5, 0.55, 0.6])
    assert rows[0]["mean"] == pytest.approx(0.1) and rows[0]["alternative"] == "two-sided"
    assert rows[0]["sign_flip_p"] == 2 / 8  # all three positive, two-sided
    assert rows[1]["b_values"] == pytest.approx([0.4, 0.3, 0.5]) and rows[1]["alternative"] == "less"
    assert rows[2]["b_values"] == pytest.approx([0.4, 0.5, 0.45])  # a left folder alone holds both variants
    assert rows[0]["archive"] == f"{seen} vs {union}" and rows[2]["archive"] == str(seen)
    assert f"{seen} vs {union}" in render(rows, union)
    main([f"--archive={union}", f"--tests=[{tests[0]}]", f"--output={tmp_path / 'h'}"])
    assert (tmp_path / "h" / "hypotheses.png").stat().st_size > 0
    with pytest.raises(FileNotFoundError, match="nowhere is not a folder"):
        HypothesesConfig(archive=seen, tests=[f"{seen}::sr!={tmp_path / 'nowhere'}::sr"])
    with pytest.raises(ValueError, match="not of the form"):
        HypothesesConfig(archive=seen, tests=["sr>>wake_only"])


def _archive(folder, finals: dict[str, list[float]]) -> None:
    """Runs ``<variant>_seed<S>`` whose final AFSR is the given value (the toy results' 0.7 shifted)."""
    from sr_imitation.io import write_checked_json
    from tests.reporting.test_results import _results

    for variant, values in finals.items():
        for seed, value in enumerate(values):
            run = folder / f"{variant}_seed{seed}"
            run.mkdir(parents=True)
            write_checked_json(run / "results.json", _results(seed=seed, shift=value - 0.7, sleep=variant == "sr"))


def test_a_named_test_carries_its_protocol_name_into_the_table_and_figure(tmp_path):
    """``M1=sr>wake_only``: the same test as ``sr>wake_only``, headed by the name the protocol gives it."""
    from sr_imitation.experiments.hypotheses import HypothesesConfig, main, render, run_tests

    first, second = tmp_path / "one", tmp_path / "two"
    _archive(first, {"sr": [0.7, 0.6, 0.65], "wake_only": [0.5, 0.55, 0.4], "replay": [0.6, 0.7, 0.5]})
    _archive(second, {"sr": [0.3, 0.4, 0.35], "wake_only": [0.3, 0.2, 0.4]})
    named = run_tests(HypothesesConfig(archive=first, holm=True,
                                       tests=["M1=sr>wake_only", "M2=sr!=replay", f"N1={second}::sr>wake_only"]))
    plain = run_tests(HypothesesConfig(archive=first, holm=True,
                                       tests=["sr>wake_only", "sr!=replay", f"{second}::sr>wake_only"]))
    assert [r["name"] for r in named] == ["M1", "M2", "N1"] and [r["name"] for r in plain] == [None] * 3
    for a, b in zip(named, plain, strict=True):  # the name changes nothing else
        assert {k: v for k, v in a.items() if k not in ("name", "test")} == \
            {k: v for k, v in b.items() if k not in ("name", "test")}
    text = render(named, first)
    assert "| M1: sr>wake_only (greater) |" in text and "| M2: sr!=replay (two-sided) |" in text
    assert f"| N1: {second}::sr>wake_only (greater) |" in text
    main([f"--archive={first}", "--tests=[M1=sr>wake_only,M2=sr!=replay]", f"--output={tmp_path / 'h'}"])
    assert (tmp_path / "h" / "hypotheses.png").stat().st_size > 0
    for bad in ("M 1=sr>wake_only", "=sr>wake_only", "M1=M2=sr>wake_only"):
        with pytest.raises(ValueError, match="not of the form"):
            HypothesesConfig(archive=first, tests=[bad])


def test_a_test_declared_on_seeds_uses_exactly_them_and_is_refused_while_one_is_missing(tmp_path, capsys):
    """``M1=sr>wake_only@0-2``: the protocol's seeds; a missing run refuses the test before any statistic (and
    names what is missing); a seed beyond the declared ones is left out."""
    from sr_imitation.experiments.hypotheses import HypothesesConfig, main, run_tests
    from sr_imitation.infra.cli_errors import run_cli

    archive, other = tmp_path / "a", tmp_path / "b"
    _archive(archive, {"sr": [0.7, 0.6, 0.65, 0.5], "wake_only": [0.5, 0.55, 0.4, 0.6], "replay": [0.6, 0.7]})
    _archive(other, {"sr": [0.5, 0.4, 0.6]})
    _archive(three := tmp_path / "three", {"sr": [0.7, 0.6, 0.65], "wake_only": [0.5, 0.55, 0.4]})
    row, = run_tests(HypothesesConfig(archive=archive, tests=["M1=sr>wake_only@0-2"]))
    assert row["seeds"] == [0, 1, 2] and row["n"] == 3  # seed 3 (a negative pair) is not declared
    same, = run_tests(HypothesesConfig(archive=three, tests=["sr>wake_only"]))
    assert (row["mean"], row["p"], row["sign_flip_p"]) == (same["mean"], same["p"], same["sign_flip_p"])
    assert run_tests(HypothesesConfig(archive=archive, tests=["sr>wake_only"]))[0]["n"] == 4  # undeclared: all
    with pytest.raises(ValueError, match=r"declared on seeds 0-2.*replay seeds \[2\]"):
        run_tests(HypothesesConfig(archive=archive, tests=["M2=sr!=replay@0-2"]))
    with pytest.raises(ValueError, match=r"sr seeds \[3\] \(in .*b\)"):  # one variant across two archives
        run_tests(HypothesesConfig(archive=archive, tests=[f"{archive}::sr!={other}::sr@0-3"]))
    with pytest.raises(ValueError, match="seed range 3-1 is empty"):
        HypothesesConfig(archive=archive, tests=["sr>wake_only@3-1"])
    out = tmp_path / "h"
    with pytest.raises(SystemExit):
        run_cli("hypotheses", main, [f"--archive={archive}", "--tests=[M1=sr>wake_only@0-3,M2=sr!=replay@0-2]",
                                     f"--output={out}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "M2=sr!=replay@0-2" in err[0] and not out.exists()  # nothing written
