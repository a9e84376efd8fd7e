"""Nash bargaining (Eq. 1): closed forms, invariances, agreement with SciPy, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from sr_imitation.core.aggregation import (
    MeanAggregator,
    NashAggregator,
    PCGradAggregator,
    frank_wolfe_nash,
    make_aggregator,
    nash_objective,
    nash_weights,
    normalized_gram,
)


def _gram(j: np.ndarray) -> np.ndarray:
    return j @ j.T


def _direction(result, j: np.ndarray) -> np.ndarray:
    return result.weights @ j


def _assert_on_simplex(alpha: np.ndarray) -> None:
    assert np.all(alpha >= 0.0)
    assert abs(alpha.sum() - 1.0) < 1e-9


def test_single_memory_gets_all_weight():
    j = np.array([[3.0, 4.0]])
    r = nash_weights(_gram(j))
    assert r.alpha.tolist() == [1.0]
    np.testing.assert_allclose(_direction(r, j), j[0] / (5.0 + 1e-5))


@pytest.mark.parametrize("cosine", [-1.0, -0.99, -0.5, 0.0, 0.3, 0.999, 1.0])
def test_two_memories_of_equal_norm_get_exactly_one_half(cosine):
    g1 = np.array([1.0, 0.0, 0.0])
    g2 = np.array([cosine, np.sqrt(max(0.0, 1 - cosine**2)), 0.0])
    agg = NashAggregator(iterations=5)
    agg._alpha_prev = np.array([0.9, 0.1])  # a warm start far from the optimum does not matter for k = 2
    assert agg(_gram(np.stack([g1, g2]))).alpha.tolist() == [0.5, 0.5]
    if abs(cosine) < 1.0:
        # Frank-Wolfe itself (no k = 2 special case) reaches the same point from any start.
        g_hat, _ = normalized_gram(_gram(np.stack([g1, g2])))
        alpha, _, _ = frank_wolfe_nash(g_hat, np.array([0.9, 0.1]), max_iters=20, tol=1e-12)
        np.testing.assert_allclose(alpha, [0.5, 0.5], atol=1e-9)


@pytest.mark.parametrize("cosine", [-0.9, 0.2, 0.95])
@pytest.mark.parametrize("scales", [(1.0, 1e4), (7.0, 0.2), (1e-1, 1e6)])
def test_two_memories_of_any_scale_get_one_half(cosine, scales):
    g1 = np.array([1.0, 0.0]) * scales[0]
    g2 = np.array([cosine, np.sqrt(1 - cosine**2)]) * scales[1]
    assert nash_weights(_gram(np.stack([g1, g2]))).alpha.tolist() == [0.5, 0.5]


@pytest.mark.parametrize("seed", range(5))
def test_invariant_to_rescaling_any_gradient(seed):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(3, 9))
    j = rng.normal(size=(k, 200))
    base = NashAggregator(iterations=500, tol=1e-12)(_gram(j)).alpha
    scales = rng.choice([1e-1, 1.0, 30.0, 1e3, 1e6], size=k)
    scaled = NashAggregator(iterations=500, tol=1e-12)(_gram(j * scales[:, None])).alpha
    np.testing.assert_allclose(scaled, base, rtol=0, atol=1e-12)
    # ... and the combined direction is the same after undoing the scales.
    r = NashAggregator(iterations=500, tol=1e-12)(_gram(j * scales[:, None]))
    np.testing.assert_allclose(r.weights * scales, NashAggregator(iterations=500, tol=1e-12)(_gram(j)).weights,
                               rtol=1e-4, atol=1e-9)


def _scipy_reference(g_hat: np.ndarray, seed: int) -> float:
    rng = np.random.default_rng(seed)
    k = g_hat.shape[0]
    best = -np.inf
    for _ in range(4):
        res = minimize(
            lambda a: -nash_objective(a, g_hat),
            rng.dirichlet(np.ones(k)),
            method="SLSQP",
            bounds=[(0.0, 1.0)] * k,
            constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1.0}],
            options={"maxiter": 1000, "ftol": 1e-14},
        )
        best = max(best, -float(res.fun))
    return best


@pytest.mark.parametrize("seed", range(12))
def test_matches_scipy_reference_up_to_k16(seed):
    rng = np.random.default_rng(100 + seed)
    k = int(rng.integers(2, 17))
    n = int(rng.choice([64, 256, 1000]))
    j = rng.normal(size=(k, n)) * rng.lognormal(size=(k, 1))
    gram = _gram(j)
    r = NashAggregator(iterations=3000, tol=1e-12)(gram)
    norms = np.sqrt(np.diag(gram))
    g_hat = gram / np.outer(norms, norms)  # the unit-direction (cosine) Gram the solver bargains over
    ref = _scipy_reference(g_hat, seed)
    assert abs(r.objective - ref) < 1e-4, (k, n, r.objective, ref)
    _assert_on_simplex(r.alpha)
    # KKT / duality gap: at the optimum the partial derivatives are <= k, equal to k on the support.
    u = g_hat @ r.alpha
    grad = g_hat @ (1.0 / (u + 1e-5))
    assert grad.max() <= k * (1 + 1e-4)


def test_objective_never_decreases_along_iterations():
    rng = np.random.default_rng(7)
    j = rng.normal(size=(6, 50))
    g_hat, _ = normalized_gram(_gram(j))
    alpha = np.full(6, 1 / 6)
    values = [nash_objective(alpha, g_hat)]
    for _ in range(30):
        alpha, _, _ = frank_wolfe_nash(g_hat, alpha, max_iters=1, tol=0.0)
        values.append(nash_objective(alpha, g_hat))
        _assert_on_simplex(alpha)
    assert all(b >= a - 1e-12 for a, b in zip(values, values[1:], strict=False))
    assert values[-1] > values[0]


def test_warm_start_is_kept_and_converged_solve_returns_immediately():
    rng = np.random.default_rng(3)
    j = rng.normal(size=(5, 100))
    agg = NashAggregator(iterations=200)
    first = agg(_gram(j))
    second = agg(_gram(j))
    assert second.iterations == 0
    np.testing.assert_array_equal(first.alpha, second.alpha)
    agg.reset()
    assert agg(_gram(j)).iterations > 0


def test_permutation_equivariance():
    rng = np.random.default_rng(11)
    j = rng.normal(size=(5, 40))
    perm = np.array([3, 0, 4, 1, 2])
    a = NashAggregator(iterations=2000, tol=1e-12)(_gram(j)).alpha
    b = NashAggregator(iterations=2000, tol=1e-12)(_gram(j[perm])).alpha
    np.testing.assert_allclose(b, a[perm], atol=1e-6)


def test_identical_gradients_keep_the_warm_start_and_give_the_common_direction():
    g = np.array([1.0, 2.0, -1.0])
    j = np.stack([g, g, g])
    agg = NashAggregator(iterations=50)
    agg._alpha_prev = np.array([0.2, 0.3, 0.5])
    r = agg(_gram(j))
    np.testing.assert_allclose(r.alpha, [0.2, 0.3, 0.5])
    np.testing.assert_allclose(_direction(r, j), g / (np.linalg.norm(g) + 1e-5), rtol=1e-9)


def test_opposite_gradients_give_a_zero_direction():
    g = np.array([0.5, -2.0, 1.0])
    j = np.stack([g, -3.0 * g])
    r = nash_weights(_gram(j))
    np.testing.assert_allclose(r.alpha, [0.5, 0.5], atol=1e-9)
    # Equal weights on g_i / (||g_i|| + eps): the residual is of the order of eps.
    assert np.linalg.norm(_direction(r, j)) < 1e-5


def test_three_memories_with_an_exact_conflict_stay_finite_and_feasible():
    g = np.array([1.0, 0.0, 0.0])
    h = np.array([0.0, 1.0, 0.0])
    j = np.stack([g, -g, h])
    r = NashAggregator(iterations=50)(_gram(j))
    _assert_on_simplex(r.alpha)
    assert np.isfinite(r.weights).all()
    d = _direction(r, j)
    # The conflicting pair is balanced (their agreement with d stays symmetric) and h is followed.
    assert abs(d[0]) < 1e-3 and d[1] > 0


def test_zero_gradients_are_masked():
    rng = np.random.default_rng(5)
    j = rng.normal(size=(4, 30))
    j[2] = 0.0
    r = NashAggregator(iterations=100)(_gram(j))
    assert r.alpha[2] == 0.0 and r.weights[2] == 0.0 and not r.active[2]
    _assert_on_simplex(r.alpha)
    all_zero = NashAggregator()(np.zeros((3, 3)))
    assert np.all(all_zero.weights == 0.0)
    _assert_on_simplex(all_zero.alpha)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_gram_is_a_clear_error(bad):
    gram = np.eye(3)
    gram[1, 1] = bad
    for agg in (NashAggregator(), MeanAggregator(), PCGradAggregator()):
        with pytest.raises(ValueError, match=r"non-finite entries in rows \[1\]"):
            agg(gram)


def test_bad_shapes_and_settings_are_rejected():
    with pytest.raises(ValueError, match="square"):
        nash_weights(np.ones((2, 3)))
    with pytest.raises(ValueError, match="symmetric"):
        nash_weights(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="iterations"):
        NashAggregator(iterations=0)
    with pytest.raises(ValueError, match="unknown aggregator"):
        make_aggregator("cagrad")


def test_mean_aggregator_is_the_mean_of_normalized_gradients():
    rng = np.random.default_rng(2)
    j = rng.normal(size=(4, 10)) * np.array([[1.0], [10.0], [0.1], [3.0]])
    r = MeanAggregator()(_gram(j))
    expected = (j / (np.linalg.norm(j, axis=1, keepdims=True) + 1e-5)).mean(axis=0)
    np.testing.assert_allclose(_direction(r, j), expected, rtol=1e-10)
    two = j[:2]
    np.testing.assert_allclose(MeanAggregator()(_gram(two)).weights, nash_weights(_gram(two)).weights)


def test_pcgrad_removes_conflicts_and_is_seeded():
    g1 = np.array([1.0, 0.0])
    g2 = np.array([-0.6, 0.8])  # conflicts with g1
    j = np.stack([g1, g2])
    d = _direction(PCGradAggregator()(_gram(j)), j)
    assert d @ g1 > 0 and d @ g2 > 0
    # No conflict: PCGrad is the plain mean.
    j2 = np.stack([g1, np.array([0.6, 0.8])])
    np.testing.assert_allclose(PCGradAggregator()(_gram(j2)).weights, MeanAggregator()(_gram(j2)).weights)
    rng = np.random.default_rng(0)
    j3 = rng.normal(size=(6, 4))
    a, b = PCGradAggregator(seed=3), PCGradAggregator(seed=3)
    np.testing.assert_array_equal(a(_gram(j3)).weights, b(_gram(j3)).weights)
