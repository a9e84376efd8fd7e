"""AFSR, PRS, BWT (both references), SPI and mean +- SEM against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sr_imitation.core.metrics import (
    afsr_curve,
    all_pairs,
    bwt_curve,
    mean_sem,
    policy_motion,
    prs_curve,
    spi_at_stage,
    stream_metrics,
    subspace_preservation,
)

NAN = float("nan")
S = [
    [0.9, NAN, NAN],
    [0.5, 0.8, NAN],
    [0.2, 0.6, 1.0],
]


def test_afsr_by_hand():
    np.testing.assert_allclose(afsr_curve(S), [0.9, 0.65, 0.6])


def test_bwt_by_hand():
    out = bwt_curve(S)
    assert math.isnan(out[0])
    np.testing.assert_allclose(out[1:], [0.5 - 0.9, ((0.2 - 0.9) + (0.6 - 0.8)) / 2])


def test_bwt_wake_uses_the_after_wake_reference():
    """S[i, i] is measured after sleep i; W_i before it. Here sleep 1 raised skill 1 from 0.6 to 0.9 (a gain that
    ``bwt`` later counts as forgetting) and sleep 2 lowered skill 2 from 0.95 to 0.8 (invisible to ``bwt``)."""
    wake = [0.6, 0.95, 0.7]
    out = bwt_curve(S, wake)
    assert math.isnan(out[0])
    np.testing.assert_allclose(out[1:], [0.5 - 0.6, ((0.2 - 0.6) + (0.6 - 0.95)) / 2])
    assert out[2] != pytest.approx(bwt_curve(S)[2])
    # The diagonal as reference is exactly the after-stage BWT (a stream without sleep), and the last skill's
    # after-wake value is never used (NaN is allowed there).
    np.testing.assert_array_equal(bwt_curve(S, np.diag(np.array(S))), bwt_curve(S))
    np.testing.assert_array_equal(bwt_curve(S, [0.6, 0.95, NAN]), out)
    with pytest.raises(ValueError, match="3 x 3"):
        bwt_curve(S, [0.6, 0.95])
    with pytest.raises(ValueError, match="every skill but the last"):
        bwt_curve(S, [0.6, NAN, 0.7])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        bwt_curve(S, [0.6, 1.2, 0.7])


def test_prs_uses_only_pairs_of_learned_skills():
    skills = ["a", "b", "c"]
    pairs = [("a", "b"), ("b", "c"), ("a", "c")]
    out = prs_curve(S, skills, pairs)
    assert math.isnan(out[0])
    assert out[1] == pytest.approx(min(0.5, 0.8))  # only (a, b) is learned at k = 2
    assert out[2] == pytest.approx((0.2 + 0.6 + 0.2) / 3)
    # A pair list without any complete pair at k = 2 leaves PRS undefined there.
    assert math.isnan(prs_curve(S, skills, [("b", "c")])[1])


def test_pairs_match_names_exactly_and_unknown_names_are_refused():
    full = np.tril(np.full((3, 3), 0.5))
    assert prs_curve(full, ["a", "b", "c"], [("a", "c")])[2] == 0.5
    assert len(all_pairs(list("abcdefgh"))) == 28
    with pytest.raises(ValueError, match="not in the stream"):
        prs_curve(full, ["a-v3", "b", "c"], [("a", "b")])  # the core knows no naming scheme


def test_bad_success_matrices_are_rejected():
    with pytest.raises(ValueError, match="NaN on or below"):
        afsr_curve([[0.5, NAN], [NAN, 0.5]])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        afsr_curve([[1.5]])
    with pytest.raises(ValueError, match="K x K"):
        afsr_curve([[0.5, 0.5]])


def _trajectory(basis: np.ndarray, rng: np.random.Generator, t: int = 200) -> np.ndarray:
    coeffs = rng.normal(size=(t, basis.shape[1])) * np.array([5.0, 3.0, 2.0])[: basis.shape[1]]
    return coeffs @ basis.T + 0.01 * rng.normal(size=(t, basis.shape[0])) + 7.0


def test_spi_identical_orthogonal_and_partial_subspaces():
    rng = np.random.default_rng(0)
    eye = np.eye(6)
    ref = _trajectory(eye[:, [0, 1, 2]], rng)
    assert subspace_preservation(ref, _trajectory(eye[:, [0, 1, 2]], rng)) == pytest.approx(1.0, abs=1e-4)
    assert subspace_preservation(ref, _trajectory(eye[:, [3, 4, 5]], rng)) == pytest.approx(0.0, abs=1e-4)
    assert subspace_preservation(ref, _trajectory(eye[:, [0, 1, 4]], rng)) == pytest.approx(2 / 3, abs=1e-3)
    # A rotation by 60 degrees of one direction inside a 2-D plane gives cos^2 = 1/4 for that direction.
    c, s = 0.5, math.sqrt(3) / 2
    rotated = np.stack([eye[:, 0], eye[:, 1], c * eye[:, 2] + s * eye[:, 3]], axis=1)
    assert subspace_preservation(ref, _trajectory(rotated, rng)) == pytest.approx((1 + 1 + 0.25) / 3, abs=1e-3)


def test_spi_at_stage_averages_earlier_skills():
    rng = np.random.default_rng(1)
    eye = np.eye(5)
    ref = {"a": _trajectory(eye[:, :3], rng), "b": _trajectory(eye[:, :3], rng)}
    cur = {"a": _trajectory(eye[:, :3], rng), "b": _trajectory(eye[:, 2:], rng)}
    assert spi_at_stage(ref, cur, ["a", "b"]) == pytest.approx((1 + 1 / 3) / 2, abs=1e-3)
    assert math.isnan(spi_at_stage(ref, cur, []))
    with pytest.raises(ValueError, match=r"skills \['c'\]"):
        spi_at_stage(ref, cur, ["c"])


def test_spi_reference_scores_one_and_a_still_policy_zero():
    rng = np.random.default_rng(2)
    eye = np.eye(7)
    ref = _trajectory(eye[:, :3], rng)
    assert subspace_preservation(ref, ref) == pytest.approx(1.0, abs=1e-12)
    # A policy that does not move: exactly constant, or constant up to noise far below the reference's motion.
    assert subspace_preservation(ref, np.full((50, 7), 3.0)) == 0.0
    still = 3.0 + 1e-3 * rng.normal(size=(50, 7))  # variance 1e-6 vs the reference's 25: below the 1e-3 floor
    assert subspace_preservation(ref, still) == 0.0
    # Moving along one of the reference's three directions only keeps one third of its subspace.
    line = np.outer(np.linspace(-4, 4, 60), eye[:, 0]) + 1e-4 * rng.normal(size=(60, 7))
    assert subspace_preservation(ref, line) == pytest.approx(1 / 3, abs=1e-6)
    # Reference directions without variance do not count either: a reference moving along one line is fully
    # preserved by a policy moving along the same line and in other directions.
    assert subspace_preservation(line, ref) == pytest.approx(1.0, abs=1e-6)
    # A reference that does not move has nothing to preserve: undefined, and left out of SPI_k.
    assert math.isnan(subspace_preservation(np.zeros((20, 7)), ref))
    spi = spi_at_stage({"a": ref, "b": np.zeros((20, 7))}, {"a": line, "b": ref}, ["a", "b"])
    assert spi == pytest.approx(1 / 3, abs=1e-6)
    assert math.isnan(spi_at_stage({"b": np.zeros((20, 7))}, {"b": ref}, ["b"]))


def test_spi_floor_is_relative_to_the_reference_and_length_independent():
    rng = np.random.default_rng(3)
    eye = np.eye(5)
    ref = _trajectory(eye[:, :3], rng, t=200)
    # The same motion scaled down 10x (variance 1/100 of the reference's) still counts; 100x (1e-4) does not.
    assert subspace_preservation(ref, 0.1 * ref) == pytest.approx(1.0, abs=1e-9)
    assert subspace_preservation(ref, 0.01 * ref) == 0.0
    # Variances, not raw squared singular values: repeating the current trajectory 10x changes nothing.
    cur = _trajectory(eye[:, [0, 1, 4]], rng, t=30)
    assert subspace_preservation(ref, np.tile(cur, (10, 1))) == pytest.approx(subspace_preservation(ref, cur),
                                                                              abs=1e-9)


def test_policy_motion_removes_each_episodes_start_and_keeps_only_the_features():
    a = np.array([[1.0, 10.0, 5.0], [2.0, 10.0, 7.0], [4.0, 11.0, 7.0]])
    b = np.array([[-3.0, 0.0, 1.0], [-3.0, 2.0, 0.0]])
    out = policy_motion([a, b], [0, 2])
    np.testing.assert_array_equal(out, [[0, 0], [1, 2], [3, 2], [0, 0], [0, -1]])
    # Episodes that start in different places but do not move give an all-zero trajectory (SPI 0).
    starts = [np.tile(np.array([x, 2 * x, 0.5]), (5, 1)) for x in (0.0, 1.0, 3.0)]
    assert not np.any(policy_motion(starts, [0, 1, 2]))
    with pytest.raises(ValueError, match=r"indices \[3\] out of range"):
        policy_motion([a], [0, 3])
    with pytest.raises(ValueError, match="at least one episode"):
        policy_motion([], [0])


def test_mean_sem_by_hand():
    m, se = mean_sem([0.2, 0.4, 0.6])
    assert m == pytest.approx(0.4) and se == pytest.approx(0.2 / math.sqrt(3))
    assert mean_sem([0.3])[0] == 0.3 and math.isnan(mean_sem([0.3])[1])
    assert math.isnan(mean_sem([])[0])
    assert mean_sem([0.1, NAN, 0.3])[0] == pytest.approx(0.2)


def test_stream_metrics_bundles_curves_and_finals():
    out = stream_metrics(S, ["a", "b", "c"], [("a", "b")], spi=[NAN, 0.9, 0.8])
    assert out["afsr"] == pytest.approx(0.6) and out["spi"] == 0.8
    assert len(out["prs_curve"]) == 3 and out["prs"] == pytest.approx(0.2)
    assert "bwt_wake" not in out
    both = stream_metrics(S, ["a", "b", "c"], [("a", "b")], wake_diagonal=[0.6, 0.95, 0.7])
    assert set(both) == {f"{m}{suffix}" for m in ("afsr", "prs", "bwt", "bwt_wake") for suffix in ("", "_curve")}
    assert both["bwt_wake"] == pytest.approx(((0.2 - 0.6) + (0.6 - 0.95)) / 2)
    assert both["bwt"] == pytest.approx(((0.2 - 0.9) + (0.6 - 0.8)) / 2)
