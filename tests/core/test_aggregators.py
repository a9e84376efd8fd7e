"""The other aggregators: raw-gradient mean (the paper's Mean-grad ablation), mean of normalized gradients,
PCGrad with and without the rescaling of the paper's baseline."""

from __future__ import annotations

import numpy as np
import pytest

from sr_imitation.core.aggregation import (
    AGGREGATORS,
    MeanGradAggregator,
    MeanNormalizedAggregator,
    PCGradAggregator,
    make_aggregator,
    nash_weights,
)
from sr_imitation.core.sleep import SleepConfig


def _gram(j: np.ndarray) -> np.ndarray:
    return j @ j.T


def test_registry_names():
    assert sorted(AGGREGATORS) == ["mean_grad", "mean_normalized", "nash", "nash_fw", "pcgrad"]
    assert SleepConfig(aggregator="nash_fw", fw_iterations=5).make_aggregator().iterations == 5
    assert SleepConfig(aggregator="pcgrad", seed=4).make_aggregator().seed == 4
    with pytest.raises(ValueError, match="mean_grad"):
        SleepConfig(aggregator="mean")


def test_mean_grad_is_the_raw_mean_and_follows_the_largest_gradient():
    rng = np.random.default_rng(2)
    j = rng.normal(size=(4, 10)) * np.array([[1.0], [100.0], [0.1], [3.0]])
    r = MeanGradAggregator()(_gram(j))
    np.testing.assert_allclose(r.weights @ j, j.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(r.alpha, np.full(4, 0.25))
    # Scale sensitivity (the paper's argument for Nash): the direction is nearly the large memory's gradient.
    d = r.weights @ j
    cos_big = d @ j[1] / (np.linalg.norm(d) * np.linalg.norm(j[1]))
    assert cos_big > 0.99
    nash = nash_weights(_gram(j))
    dn = nash.weights @ j
    assert dn @ j[1] / (np.linalg.norm(dn) * np.linalg.norm(j[1])) < 0.9


def test_mean_normalized_is_the_mean_of_normalized_gradients_and_equals_nash_for_two():
    rng = np.random.default_rng(2)
    j = rng.normal(size=(4, 10)) * np.array([[1.0], [10.0], [0.1], [3.0]])
    r = MeanNormalizedAggregator()(_gram(j))
    expected = (j / (np.linalg.norm(j, axis=1, keepdims=True) + 1e-5)).mean(axis=0)
    np.testing.assert_allclose(r.weights @ j, expected, rtol=1e-10)
    two = j[:2]
    np.testing.assert_allclose(MeanNormalizedAggregator()(_gram(two)).weights, nash_weights(_gram(two)).weights)
    assert not np.allclose(MeanGradAggregator()(_gram(two)).weights, nash_weights(_gram(two)).weights)


def test_pcgrad_removes_conflicts_and_is_seeded():
    g1 = np.array([1.0, 0.0])
    g2 = np.array([-0.6, 0.8])  # conflicts with g1
    j = np.stack([g1, g2])
    d = PCGradAggregator()(_gram(j)).weights @ j
    assert d @ g1 > 0 and d @ g2 > 0
    j2 = np.stack([g1, np.array([0.6, 0.8])])  # no conflict: PCGrad is the plain normalized mean
    np.testing.assert_allclose(PCGradAggregator()(_gram(j2)).weights, MeanNormalizedAggregator()(_gram(j2)).weights)
    j3 = np.random.default_rng(0).normal(size=(6, 4))
    a, b = PCGradAggregator(seed=3), PCGradAggregator(seed=3)
    np.testing.assert_array_equal(a(_gram(j3)).weights, b(_gram(j3)).weights)


@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_pcgrad_rescale_gives_the_projected_direction_the_raw_update_norm(reduction):
    rng = np.random.default_rng(1)
    j = rng.normal(size=(5, 8)) * np.array([[1.0], [20.0], [0.5], [3.0], [7.0]])
    plain = PCGradAggregator(seed=2, reduction=reduction)(_gram(j))
    scaled = PCGradAggregator(seed=2, reduction=reduction, rescale=True)(_gram(j))
    d_plain, d_scaled = plain.weights @ j, scaled.weights @ j
    raw = j.mean(axis=0) if reduction == "mean" else j.sum(axis=0)
    np.testing.assert_allclose(np.linalg.norm(d_scaled), np.linalg.norm(raw), rtol=1e-10)
    # Same direction as the plain projected update, only longer or shorter.
    np.testing.assert_allclose(d_scaled / np.linalg.norm(d_scaled), d_plain / np.linalg.norm(d_plain), atol=1e-10)
    assert abs(np.linalg.norm(d_plain) - np.linalg.norm(raw)) > 1e-3  # the rescale did something
    assert "rescale=True" in repr(PCGradAggregator(rescale=True))


def test_make_aggregator_passes_options():
    assert make_aggregator("pcgrad", rescale=True).rescale is True
    assert make_aggregator("nash", max_iterations=7).max_iterations == 7


def _calls(aggregator, grams):
    return [(r.weights.tolist(), r.alpha.tolist(), r.iterations) for r in map(aggregator, grams)]


@pytest.mark.parametrize("name", sorted(AGGREGATORS))
def test_an_aggregator_restored_from_its_state_continues_as_the_original(name):
    """state() (through JSON, as a wake snapshot stores it) and load_state() on a fresh aggregator of the same
    settings: its next calls return exactly what the original's would (weights, alpha, solver iterations)."""
    import json

    rng = np.random.default_rng(11)
    base = rng.normal(size=(4, 12))  # a slowly moving family of conflicting gradients, as in a wake
    grams = [_gram(base + 0.05 * rng.normal(size=base.shape)) for _ in range(8)]
    original = make_aggregator(name)
    _calls(original, grams[:4])
    restored = make_aggregator(name)
    restored.load_state(json.loads(json.dumps(original.state())))
    assert _calls(restored, grams[4:]) == _calls(original, grams[4:])
    if name in ("nash", "nash_fw", "pcgrad"):  # stateful: a fresh one differs (warm start, projection order)
        fresh = make_aggregator(name)
        again = make_aggregator(name)
        _calls(again, grams[:4])
        assert _calls(fresh, grams[4:]) != _calls(again, grams[4:])
