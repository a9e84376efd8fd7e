"""Nash bargaining (Eq. 1): exact maximizer on conflicting memories, the answer when no direction agrees,
invariances, warm start, the Frank-Wolfe ablation, and degenerate inputs.

The reference is independent of the solver: SciPy SLSQP on Eq. 1 with the agreement constraints C alpha >= 0,
started from the point an LP finds with the largest agreement margin (so it starts inside the domain).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from sr_imitation.benchmarks.nash import agreement_margin, scipy_reference
from sr_imitation.core.aggregation import (
    FrankWolfeNashAggregator,
    NashAggregator,
    cosine_matrix,
    frank_wolfe_nash,
    make_aggregator,
    min_norm_point,
    nash_objective,
    nash_weights,
    solve_nash,
)
from sr_imitation.core.aggregation._gram import gradient_norms

EPS = 1e-5


def _gram(j: np.ndarray) -> np.ndarray:
    return j @ j.T


def _unit(j: np.ndarray) -> np.ndarray:
    return j / np.linalg.norm(j, axis=1, keepdims=True)


def _cos(j: np.ndarray) -> np.ndarray:
    g = _gram(j)
    return cosine_matrix(g, np.ones(len(j), dtype=bool), gradient_norms(g))


def _agreement(result, j: np.ndarray) -> np.ndarray:
    """u_i = <g_hat_i, d> for the bargained direction d = sum_j alpha_j g_hat_j on exact unit directions (the
    applied direction uses g / (||g|| + eps) and differs by O(eps / ||g||))."""
    u = _unit(j)
    return u @ (result.alpha @ u)


def _assert_on_simplex(alpha: np.ndarray) -> None:
    assert np.all(alpha >= 0.0)
    assert abs(alpha.sum() - 1.0) < 1e-9


def _scipy_reference(c: np.ndarray, start: np.ndarray) -> float:
    return nash_objective(scipy_reference(c, start, EPS), c)


def _scipy_min_norm(c: np.ndarray) -> float:
    k = c.shape[0]
    res = minimize(lambda a: a @ c @ a, np.full(k, 1 / k), jac=lambda a: 2 * c @ a, method="SLSQP",
                   bounds=[(0, 1)] * k, constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1}],
                   options={"ftol": 1e-15, "maxiter": 1000})
    return float(res.fun)


def _conflict(rng: np.random.Generator, k: int, d: int) -> np.ndarray:
    """The conflicting family: k unit gradients in d dims, memory 0 opposing the mean of the others."""
    j = rng.normal(size=(k, d))
    j[0] = -j[1:].mean(axis=0) + 0.5 * rng.normal(size=d)
    return _unit(j) * rng.lognormal(size=(k, 1))  # arbitrary scales: the solver must not care


def _family(seed: int, n: int, ks=range(2, 17), conflict_share: float = 0.6) -> list[np.ndarray]:
    """Jacobians k x d: conflicting (low-dimensional, one memory opposing) and generic Gaussian, k = 2..16."""
    rng = np.random.default_rng(seed)
    out = []
    ks = list(ks)
    while len(out) < n:
        k = int(rng.choice(ks))
        if rng.random() < conflict_share:
            out.append(_conflict(rng, k, int(rng.integers(3, 8))))
        else:
            out.append(rng.normal(size=(k, int(rng.choice([8, 64, 256])))) * rng.lognormal(size=(k, 1)))
    return out


# --- exactness on families with conflicts ------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_matches_the_constrained_scipy_reference_whenever_an_agreeing_direction_exists(seed):
    checked = 0
    for j in _family(seed, 40):
        c = _cos(j)
        margin, start = agreement_margin(c)
        if margin < 1e-3:
            continue
        checked += 1
        r = NashAggregator(warm_start=False)(_gram(j))
        _assert_on_simplex(r.alpha)
        assert r.status in ("optimal", "closed_form"), r.status
        ours = nash_objective(r.alpha, c)
        ref = _scipy_reference(c, start)
        # Within 1e-6 relative of the maximum (and never below the reference by more).
        assert ours >= ref - 1e-6 * abs(ref), (len(j), ours, ref)
        assert _agreement(r, j).min() >= 0.0
    assert checked >= 15


@pytest.mark.parametrize("seed", range(3))
def test_duality_gap_certificate_and_kkt_conditions(seed):
    for j in _family(100 + seed, 30):
        c = _cos(j)
        if len(j) < 3 or agreement_margin(c)[0] < 1e-3:
            continue
        sol = solve_nash(c)
        u = c @ sol.alpha
        grad = c @ (1.0 / (u + EPS))
        lam = sol.alpha @ grad
        support = sol.alpha > 0
        # KKT of max f on the simplex: partial derivatives equal on the support, not larger outside it.
        scale = max(1.0, abs(sol.objective))
        assert grad.max() - lam <= 1e-9 * scale
        assert np.abs(grad[support] - lam).max() <= 1e-6 * max(1.0, lam)
        assert sol.gap <= 1e-9 * scale


def test_the_maximizer_agrees_with_every_memory_when_the_margin_exceeds_k_minus_one_eps():
    # Module docstring's claim: margin tau > (k - 1) eps  =>  every u_i > 0 at the maximizer.
    rng = np.random.default_rng(7)
    seen = 0
    for _ in range(300):
        k = int(rng.integers(3, 9))
        j = _conflict(rng, k, int(rng.integers(2, 5)))
        c = _cos(j)
        margin, _ = agreement_margin(c)
        if not (k - 1) * EPS < margin < 0.05:
            continue
        seen += 1
        sol = solve_nash(c)
        assert sol.status == "optimal" and sol.min_agreement > 0.0, (margin, sol)
    assert seen >= 20


@pytest.mark.parametrize("iterations", [5, 50])
def test_frank_wolfe_ablation_can_oppose_a_memory_where_the_exact_solver_does_not(iterations):
    """Why the default is the exact solver, as a regression test: on the conflicting family the
    paper's fixed-budget Frank-Wolfe leaves some memory with negative agreement; the exact solver never does."""
    rng = np.random.default_rng(0)
    fw_negative = fw_worse = exact_negative = n = 0
    while n < 60:
        j = _conflict(rng, int(rng.integers(3, 6)), int(rng.integers(3, 8)))
        c = _cos(j)
        if agreement_margin(c)[0] < 1e-3:
            continue
        n += 1
        fw = FrankWolfeNashAggregator(iterations=iterations, warm_start=False)(_gram(j))
        exact = NashAggregator(warm_start=False)(_gram(j))
        assert fw.status == "approximate"
        _assert_on_simplex(fw.alpha)
        fw_negative += int(_agreement(fw, j).min() < 0.0)
        exact_negative += int(_agreement(exact, j).min() < 0.0)
        fw_worse += int(nash_objective(fw.alpha, c) < nash_objective(exact.alpha, c) - 1e-3)
    assert exact_negative == 0
    assert fw_negative >= 1 and fw_worse >= 5, (fw_negative, fw_worse)


# --- no agreeing direction ------------------------------------------------------------------------------------


def test_three_directions_at_120_degrees_give_a_zero_step():
    j = np.array([[1.0, 0.0], [-0.5, np.sqrt(3) / 2], [-0.5, -np.sqrt(3) / 2]]) * np.array([[1.0], [3.0], [0.2]])
    r = nash_weights(_gram(j))
    np.testing.assert_allclose(r.alpha, [1 / 3, 1 / 3, 1 / 3], atol=1e-9)
    assert np.linalg.norm(r.alpha @ _unit(j)) < 1e-9  # the bargained direction on unit gradients is 0
    assert np.linalg.norm(r.weights @ j) < 1e-4  # applied with g / (||g|| + eps): residual ~ eps / ||g||


def test_an_exact_conflict_pair_is_left_alone_while_an_orthogonal_memory_is_followed():
    g, h = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    j = np.stack([g, -2.0 * g, h])
    r = nash_weights(_gram(j))
    # Eq. 1's maximizer is alpha = (0, 0, 1): d = h opposes no memory and helps the third.
    assert r.status == "optimal"
    np.testing.assert_allclose(r.alpha, [0.0, 0.0, 1.0], atol=1e-9)
    u = _agreement(r, j)
    assert abs(u[0]) < 1e-12 and abs(u[1]) < 1e-12 and u[2] > 0.99


@pytest.mark.parametrize("seed", range(3))
def test_pareto_stationary_memories_get_the_min_norm_point_and_are_never_opposed(seed):
    """k > d random gradients: 0 is often in the hull. The answer then is the min-norm point (checked against
    SciPy's QP), and no returned direction ever opposes a memory."""
    rng = np.random.default_rng(seed)
    statuses = set()
    for _ in range(60):
        k, d = int(rng.integers(3, 17)), int(rng.integers(2, 5))
        j = rng.normal(size=(k, d)) * rng.lognormal(size=(k, 1))
        r = NashAggregator(warm_start=False)(_gram(j))
        statuses.add(r.status)
        _assert_on_simplex(r.alpha)
        assert _agreement(r, j).min() >= -1e-9
        if r.status == "pareto_stationary":
            c = _cos(j)
            assert r.alpha @ c @ r.alpha <= _scipy_min_norm(c) + 1e-9
    assert {"optimal", "pareto_stationary"} <= statuses


@pytest.mark.parametrize("seed", range(3))
def test_min_norm_point_matches_scipy(seed):
    rng = np.random.default_rng(50 + seed)
    for _ in range(20):
        k = int(rng.integers(2, 17))
        c = _cos(rng.normal(size=(k, int(rng.integers(2, 20)))))
        alpha, _ = min_norm_point(c)
        _assert_on_simplex(alpha)
        q = c @ alpha
        v = alpha @ q
        assert q.min() >= v - 1e-10  # optimality: every memory agrees with d_mn at least ||d_mn||^2
        assert v <= _scipy_min_norm(c) + 1e-10


# --- closed forms, invariances, warm start ---------------------------------------------------------------------


def test_single_memory_gets_all_weight():
    j = np.array([[3.0, 4.0]])
    r = nash_weights(_gram(j))
    assert r.alpha.tolist() == [1.0]
    np.testing.assert_allclose(r.weights @ j, j[0] / (5.0 + 1e-5))


@pytest.mark.parametrize("cosine", [-1.0, -0.99, -0.5, 0.0, 0.3, 0.999, 1.0])
@pytest.mark.parametrize("scales", [(1.0, 1.0), (1.0, 1e4), (7.0, 0.2)])
def test_two_memories_get_exactly_one_half(cosine, scales):
    g1 = np.array([1.0, 0.0, 0.0]) * scales[0]
    g2 = np.array([cosine, np.sqrt(max(0.0, 1 - cosine**2)), 0.0]) * scales[1]
    agg = NashAggregator()
    agg._alpha_prev = np.array([0.9, 0.1])  # a warm start far from the optimum does not matter for k = 2
    assert agg(_gram(np.stack([g1, g2]))).alpha.tolist() == [0.5, 0.5]
    if abs(cosine) < 1.0:  # the general solver (no k = 2 short cut) reaches the closed form from a far start
        sol = solve_nash(_cos(np.stack([g1, g2])), np.array([0.9, 0.1]))
        np.testing.assert_allclose(sol.alpha, [0.5, 0.5], atol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_invariant_to_rescaling_any_gradient(seed):
    rng = np.random.default_rng(seed)
    j = _family(200 + seed, 1, ks=range(3, 17))[0]
    base = NashAggregator(warm_start=False)(_gram(j))
    scales = rng.choice([1e-4, 1e-1, 1.0, 30.0, 1e3, 1e6], size=len(j))
    scaled = NashAggregator(warm_start=False)(_gram(j * scales[:, None]))
    np.testing.assert_allclose(scaled.alpha, base.alpha, rtol=0, atol=1e-9)
    assert scaled.status == base.status
    # ... and the applied direction is sum_j alpha_j g_j / (||g_j|| + eps) (paper's g_hat), for any scale.
    norms = np.linalg.norm(j * scales[:, None], axis=1)
    np.testing.assert_allclose(scaled.weights, scaled.alpha / (norms + EPS), rtol=1e-12)


def test_permutation_equivariance():
    rng = np.random.default_rng(11)
    for j in (rng.normal(size=(5, 40)), _conflict(rng, 6, 4)):
        perm = rng.permutation(len(j))
        a = NashAggregator(warm_start=False)(_gram(j))
        b = NashAggregator(warm_start=False)(_gram(j[perm]))
        np.testing.assert_allclose(nash_objective(b.alpha, _cos(j[perm])), nash_objective(a.alpha, _cos(j)),
                                   rtol=1e-9)
        np.testing.assert_allclose(b.weights @ j[perm], a.weights @ j, atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_warm_start_reaches_the_same_maximum_with_fewer_steps(seed):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(4, 17))
    base = rng.normal(size=(k, 64))
    warm, cold_steps, warm_steps = NashAggregator(), [], []
    for _ in range(20):
        j = base + 0.05 * rng.normal(size=base.shape)
        w = warm(_gram(j))
        cold = NashAggregator(warm_start=False)(_gram(j))
        c = _cos(j)
        np.testing.assert_allclose(nash_objective(w.alpha, c), nash_objective(cold.alpha, c), rtol=1e-9)
        cold_steps.append(cold.iterations)
        warm_steps.append(w.iterations)
    assert np.mean(warm_steps[1:]) < np.mean(cold_steps[1:])


def test_a_converged_warm_start_returns_immediately_and_reset_forgets_it():
    j = np.random.default_rng(3).normal(size=(5, 100))
    agg = NashAggregator()
    first = agg(_gram(j))
    second = agg(_gram(j))
    assert second.iterations == 0
    np.testing.assert_array_equal(first.alpha, second.alpha)
    agg.reset()
    assert agg(_gram(j)).iterations > 0


def test_warm_start_that_opposes_a_memory_is_replaced():
    rng = np.random.default_rng(4)
    while True:
        j = _conflict(rng, 4, 3)
        c = _cos(j)
        if agreement_margin(c)[0] > 1e-3 and (c @ np.array([0.0, 0.0, 0.0, 1.0])).min() < 0:
            break
    agg = NashAggregator()
    agg._alpha_prev = np.array([0.0, 0.0, 0.0, 1.0])  # a vertex whose direction opposes a memory
    r = agg(_gram(j))
    assert r.status == "optimal" and _agreement(r, j).min() > 0.0
    np.testing.assert_allclose(r.objective, nash_objective(solve_nash(c).alpha, c), rtol=1e-9)


# --- degenerate inputs -----------------------------------------------------------------------------------------


def test_identical_gradients_keep_the_warm_start_and_give_the_common_direction():
    g = np.array([1.0, 2.0, -1.0])
    j = np.stack([g, g, g])
    agg = NashAggregator()
    agg._alpha_prev = np.array([0.2, 0.3, 0.5])
    r = agg(_gram(j))
    np.testing.assert_allclose(r.alpha, [0.2, 0.3, 0.5])
    np.testing.assert_allclose(r.weights @ j, g / (np.linalg.norm(g) + 1e-5), rtol=1e-9)


def test_opposite_pair_gives_a_zero_direction():
    g = np.array([0.5, -2.0, 1.0])
    j = np.stack([g, -3.0 * g])
    r = nash_weights(_gram(j))
    np.testing.assert_allclose(r.alpha, [0.5, 0.5], atol=1e-9)
    assert np.linalg.norm(r.weights @ j) < 1e-5  # equal weights on g_i / (||g_i|| + eps): residual ~ eps


def test_zero_gradients_are_masked():
    rng = np.random.default_rng(5)
    j = rng.normal(size=(4, 30))
    j[2] = 0.0
    r = NashAggregator()(_gram(j))
    assert r.alpha[2] == 0.0 and r.weights[2] == 0.0 and not r.active[2]
    _assert_on_simplex(r.alpha)
    ref = NashAggregator()(_gram(j[[0, 1, 3]]))
    np.testing.assert_allclose(r.alpha[[0, 1, 3]], ref.alpha, atol=1e-12)
    all_zero = NashAggregator()(np.zeros((3, 3)))
    assert np.all(all_zero.weights == 0.0) and all_zero.status == "all_zero"


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("name", ["nash", "nash_fw", "mean_grad", "mean_normalized", "pcgrad"])
def test_non_finite_gram_is_a_clear_error(bad, name):
    gram = np.eye(3)
    gram[1, 1] = bad
    with pytest.raises(ValueError, match=r"non-finite entries in rows \[1\]"):
        make_aggregator(name)(gram)


def test_bad_shapes_and_settings_are_rejected():
    with pytest.raises(ValueError, match="square"):
        nash_weights(np.ones((2, 3)))
    with pytest.raises(ValueError, match="symmetric"):
        nash_weights(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="max_iterations"):
        NashAggregator(max_iterations=0)
    with pytest.raises(ValueError, match="iterations"):
        FrankWolfeNashAggregator(iterations=0)
    with pytest.raises(ValueError, match="unknown aggregator 'cagrad'"):
        make_aggregator("cagrad")
    with pytest.raises(ValueError, match="mean_grad"):
        make_aggregator("mean")  # the old name is gone, with a hint


def test_frank_wolfe_objective_never_decreases_along_iterations():
    from sr_imitation.core.aggregation import extended_nash_objective

    rng = np.random.default_rng(7)
    c = _cos(rng.normal(size=(6, 50)))
    alpha = np.full(6, 1 / 6)
    values = [extended_nash_objective(alpha, c)]
    for _ in range(30):
        alpha, _, _ = frank_wolfe_nash(c, alpha, max_iters=1, tol=0.0)
        values.append(extended_nash_objective(alpha, c))
        _assert_on_simplex(alpha)
    assert all(b >= a - 1e-12 for a, b in zip(values, values[1:], strict=False))
    assert values[-1] > values[0]


def test_repr_names_the_solver():
    assert "max_iterations=100" in repr(NashAggregator())
    assert repr(FrankWolfeNashAggregator(iterations=5)).startswith("FrankWolfeNashAggregator(iterations=5")
