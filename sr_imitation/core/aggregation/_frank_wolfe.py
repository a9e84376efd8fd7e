"""The paper's warm-started Frank-Wolfe for Eq. 1, with a fixed iteration budget: the ``nash_fw`` ablation.

The paper computes alpha* "with warm-started Frank-Wolfe iterations" (50 for MT5, 5 for SurgicAI). Kept for the
Frank-Wolfe ablation; the default ``nash`` aggregator solves Eq. 1 exactly (``_nash.py``). **This solver is
approximate**: on 200 conflicting instances with k = 3-5 where a direction agreeing with every memory exists,
50 iterations left some memory with negative agreement in 12 (5 iterations: 23), and the objective more than
1e-3 below the maximum in 89 (``python -m sr_imitation.benchmarks.nash`` measures it).

Objective. Frank-Wolfe from the uniform or warm start can sit where Eq. 1 is undefined (some u_i <= -eps_nash),
so it maximizes a continuation: ``h(u) = log(u + eps_nash)`` for u >= 0 and its second-order Taylor expansion at
0, ``log(eps_nash) + u/eps_nash - u^2/(2 eps_nash^2)``, below (our choice). The continuation is concave and C^2
and equals Eq. 1 where every memory agrees, but it replaces log(u + eps) on (-eps, 0) and its curvature
1/eps_nash^2 = 1e10 below 0 makes Frank-Wolfe stall there: the reason for the exact default.

Iteration (``../shared/notes/nash-bargaining-solver.md`` section 3): the closed-form linear oracle (the vertex of
the largest partial derivative), away steps (Lacoste-Julien & Jaggi 2015), an exact line search on the concave
1-D restriction (safeguarded Newton), the duality gap as stopping certificate. Exact line search keeps a warm
start: a step size is never forced to 1 at the first iteration as the open-loop rule 2/(t+2) would.
"""

from __future__ import annotations

import math

import numpy as np

from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS
from sr_imitation.core.aggregation._nash import NASH_EPS, NashAggregator

_NEWTON_MAX_ITERS = 60


def _h(u: np.ndarray, eps: float) -> np.ndarray:
    pos = np.maximum(u, 0.0)
    neg = np.minimum(u, 0.0)
    return np.log(pos + eps) + neg / eps - 0.5 * (neg / eps) ** 2


def _dh(u: float, eps: float) -> float:
    return 1.0 / (u + eps) if u >= 0.0 else (eps - u) / (eps * eps)


def extended_nash_objective(alpha: np.ndarray, g_hat: np.ndarray, eps_nash: float = NASH_EPS) -> float:
    """f(alpha) of Eq. 1 with the concave extension below u = 0 (module docstring), defined for every alpha."""
    return float(_h(np.asarray(g_hat) @ np.asarray(alpha, dtype=np.float64), eps_nash).sum())


def _line_search(u: list[float], delta: list[float], gamma_max: float, eps: float) -> float:
    """argmax over gamma in [0, gamma_max] of sum_i h(u_i + gamma delta_i): safeguarded Newton on the
    derivative, which is monotone decreasing because h is concave."""
    k = len(u)
    d_end = sum(delta[i] * _dh(u[i] + gamma_max * delta[i], eps) for i in range(k))
    if d_end >= 0.0:
        return gamma_max
    lo, hi, gamma = 0.0, gamma_max, 0.0
    inv_e2 = 1.0 / (eps * eps)
    for _ in range(_NEWTON_MAX_ITERS):
        d1 = d2 = 0.0
        for i in range(k):
            di = delta[i]
            v = u[i] + gamma * di
            if v >= 0.0:
                w = 1.0 / (v + eps)
                d1 += di * w
                d2 -= di * di * w * w
            else:
                d1 += di * (eps - v) * inv_e2
                d2 -= di * di * inv_e2
        if d1 > 0.0:
            lo = gamma
        else:
            hi = gamma
        if hi - lo <= 1e-12 * gamma_max:
            return gamma
        step = gamma - d1 / d2 if d2 < 0.0 else -1.0
        if not lo < step < hi:
            step = 0.5 * (lo + hi)
        if abs(step - gamma) <= 1e-12 * gamma_max:
            return step
        gamma = step
    return gamma


def frank_wolfe_nash(
    g_hat: np.ndarray,
    alpha0: np.ndarray,
    max_iters: int,
    eps_nash: float = NASH_EPS,
    tol: float = 1e-6,
    away_steps: bool = True,
) -> tuple[np.ndarray, int, float]:
    """Run Frank-Wolfe on Eq. 1 from ``alpha0``; returns ``(alpha, iterations, duality_gap)``.

    Stops after ``max_iters`` iterations or when the duality gap ``max_j grad_j - alpha . grad`` (an upper
    bound on f* - f) is at most ``tol * k``. Written in plain Python floats: for the k <= ~16 memories of a
    sleep phase this is several times faster than numpy's per-call overhead (O(k^2) per iteration).
    """
    rows = np.asarray(g_hat, dtype=np.float64).tolist()
    k = len(rows)
    alpha = [float(a) for a in alpha0]
    u = [sum(map(float.__mul__, rows[i], alpha)) for i in range(k)]
    gap = math.inf
    it = 0
    for it in range(1, max_iters + 1):
        r = [_dh(x, eps_nash) for x in u]
        grad = [sum(map(float.__mul__, rows[i], r)) for i in range(k)]
        lin = sum(map(float.__mul__, alpha, grad))
        j = max(range(k), key=grad.__getitem__)  # first index on ties: deterministic
        gap = grad[j] - lin
        if gap <= tol * k:
            return np.array(alpha), it - 1, gap
        a, away_gain = -1, -math.inf
        if away_steps:
            a = min((i for i in range(k) if alpha[i] > 0.0), key=grad.__getitem__)
            away_gain = lin - grad[a]
        if away_gain > gap and alpha[a] < 1.0:
            # Away step: move along alpha - e_a, feasible up to alpha_a / (1 - alpha_a).
            gamma_max = alpha[a] / (1.0 - alpha[a])
            col = rows[a]
            delta = [u[i] - col[i] for i in range(k)]
            gamma = _line_search(u, delta, gamma_max, eps_nash)
            alpha = [x * (1.0 + gamma) for x in alpha]
            alpha[a] = 0.0 if gamma >= gamma_max else alpha[a] - gamma  # drop step removes the vertex
        else:
            col = rows[j]
            delta = [col[i] - u[i] for i in range(k)]
            gamma = _line_search(u, delta, 1.0, eps_nash)
            alpha = [x * (1.0 - gamma) for x in alpha]
            alpha[j] += gamma
        total = sum(max(x, 0.0) for x in alpha)
        alpha = [max(x, 0.0) / total for x in alpha]
        u = [sum(map(float.__mul__, rows[i], alpha)) for i in range(k)]
    r = [_dh(x, eps_nash) for x in u]
    grad = [sum(map(float.__mul__, rows[i], r)) for i in range(k)]
    gap = max(grad) - sum(map(float.__mul__, alpha, grad))
    return np.array(alpha), it, gap


class FrankWolfeNashAggregator(NashAggregator):
    """Eq. 1 by the paper's warm-started Frank-Wolfe with a fixed budget (approximate; the ``nash_fw`` ablation).

    Args:
        iterations: Frank-Wolfe iterations per call (paper: 50 for MT5, 5 for SurgicAI).
        eps, eps_nash, warm_start, mask_tol: as for :class:`NashAggregator`.
        tol: relative duality-gap tolerance for early return (gap <= tol * k).
        away_steps: allow away steps (drop vertices from the support).
    """

    name = "nash_fw"

    def __init__(
        self,
        iterations: int = 50,
        eps: float = GRAD_NORM_EPS,
        eps_nash: float = NASH_EPS,
        tol: float = 1e-6,
        warm_start: bool = True,
        away_steps: bool = True,
        mask_tol: float = 1e-6,
    ) -> None:
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        super().__init__(eps, eps_nash, tol, iterations, warm_start, mask_tol)
        self.iterations = int(iterations)
        self.away_steps = away_steps

    def _solve(self, cosine: np.ndarray, start: np.ndarray | None) -> tuple[np.ndarray, int, float, str, float]:
        n = cosine.shape[0]
        start = np.full(n, 1.0 / n) if start is None else start
        alpha, iters, gap = frank_wolfe_nash(cosine, start, self.iterations, self.eps_nash, self.tol,
                                             self.away_steps)
        return alpha, iters, gap, "approximate", extended_nash_objective(alpha, cosine, self.eps_nash)

    def _closed_form_objective(self, cosine: np.ndarray) -> float:
        return extended_nash_objective(np.full(cosine.shape[0], 1.0 / cosine.shape[0]), cosine, self.eps_nash)

    def __repr__(self) -> str:
        return (
            f"FrankWolfeNashAggregator(iterations={self.iterations}, eps={self.eps:g}, eps_nash={self.eps_nash:g}, "
            f"warm_start={self.warm_start})"
        )
