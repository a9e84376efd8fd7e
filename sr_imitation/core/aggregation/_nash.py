"""Nash-bargained weights on the simplex (paper Eq. 1), solved by warm-started Frank-Wolfe.

Objective, with u = G_hat alpha the agreement of each normalized memory gradient with the combined direction:

    alpha* = argmax_{alpha in simplex} f(alpha),   f(alpha) = sum_i h(u_i),   u = G_hat alpha.

``h`` is ``log(u + eps_nash)`` for u >= 0 (exactly Eq. 1). Eq. 1 is undefined where a memory disagrees with the
combined direction (u < 0, which happens when gradients conflict); there we continue ``h`` by its
second-order Taylor expansion at 0, ``log(eps_nash) + u/eps_nash - u^2/(2 eps_nash^2)``. The extension is
concave and C^2, equals Eq. 1 on every alpha where all memories agree, and penalizes disagreement steeply, so
the solver is well defined for every finite input.

Normalization. The paper normalizes g_hat_i = g_i / (||g_i|| + eps). We solve the bargaining problem on the
exact unit directions (the cosine matrix of the gradients, zero gradients masked), so the weights are exactly
invariant to rescaling any gradient, and apply the paper's g_hat in the combined direction
d = sum_j alpha_j g_i / (||g_j|| + eps). The two differ only for gradients with norm comparable to eps.

Solver (see ``../shared/notes/nash-bargaining-solver.md`` section 3): Frank-Wolfe with the closed-form linear
oracle (the vertex of the largest partial derivative), away steps (Lacoste-Julien & Jaggi 2015) so that a
vertex can leave the support quickly, an exact line search on the concave 1-D restriction (safeguarded
Newton), and the duality gap as stopping certificate. Exact line search keeps a warm start: a step size is
never forced to 1 at the first iteration as the open-loop rule 2/(t+2) would.

Documented behaviour on degenerate inputs:

* k = 1 (or one non-zero gradient): alpha = [1].
* Zero gradients (``||g_hat_i||^2 < mask_tol``): masked, alpha_i = 0; they would otherwise hold warm-start mass
  that Frank-Wolfe only removes slowly. All gradients zero: alpha uniform, weights 0.
* k = 2 non-zero gradients: alpha = (1/2, 1/2) in closed form. On unit directions f is symmetric under
  alpha <-> 1 - alpha for any cosine c in [-1, 1] (also with the extension) and concave, so 1/2 is optimal
  (for c = 1 every alpha is); for c = -1 the direction is 0.
* Identical gradients: f is constant; the warm start is returned unchanged (any alpha is optimal).
* Opposite gradients (k >= 3 with an exact conflict): the extension drives the combined direction to
  (near) zero, a Pareto-stationary update, as MGDA does.
* Non-finite Gram entries: ``ValueError`` naming the rows; the sleep loop checks before calling and skips.
"""

from __future__ import annotations

import math

import numpy as np

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS, as_gram, normalized_gram

NASH_EPS = 1e-5
"""Floor eps_Nash of Eq. 1. The paper gives no value; we use the gradient-normalization constant."""

_NEWTON_MAX_ITERS = 60


def _h(u: np.ndarray, eps: float) -> np.ndarray:
    pos = np.maximum(u, 0.0)
    neg = np.minimum(u, 0.0)
    return np.log(pos + eps) + neg / eps - 0.5 * (neg / eps) ** 2


def _dh(u: float, eps: float) -> float:
    return 1.0 / (u + eps) if u >= 0.0 else (eps - u) / (eps * eps)


def nash_objective(alpha: np.ndarray, g_hat: np.ndarray, eps_nash: float = NASH_EPS) -> float:
    """f(alpha) of Eq. 1 (with the concave extension for u < 0) for a normalized Gram matrix ``g_hat``."""
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


class NashAggregator(Aggregator):
    """Nash bargaining over normalized memory gradients (Eq. 1), warm-started across calls.

    Args:
        iterations: Frank-Wolfe iterations per call (paper: 50 for MT5, 5 for SurgicAI).
        eps: gradient-normalization constant (paper: 1e-5).
        eps_nash: the floor eps_Nash of Eq. 1.
        tol: relative duality-gap tolerance for early return.
        warm_start: start each solve from the previous call's alpha (paper: enabled).
        away_steps: allow away steps (drop vertices from the support).
        mask_tol: memories with ``||g_hat_i||^2`` below this are treated as zero gradients.

    .. note:: The aggregator is stateful (warm start); call :meth:`reset` between sleep phases when the
       memory set changes. A change in k resets it automatically.
    """

    name = "nash"

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
        super().__init__(eps)
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        if not eps_nash > 0:
            raise ValueError(f"eps_nash must be > 0, got {eps_nash}")
        self.iterations = int(iterations)
        self.eps_nash = float(eps_nash)
        self.tol = float(tol)
        self.warm_start = warm_start
        self.away_steps = away_steps
        self.mask_tol = float(mask_tol)
        self._alpha_prev: np.ndarray | None = None

    def reset(self) -> None:
        self._alpha_prev = None

    def _start(self, k: int, active: np.ndarray) -> np.ndarray:
        n = int(active.sum())
        prev = self._alpha_prev
        if self.warm_start and prev is not None and prev.shape == (k,):
            start = prev[active]
            if start.sum() > 0.0 and np.isfinite(start).all():
                return start / start.sum()
        return np.full(n, 1.0 / n)

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        g_hat, scale = normalized_gram(gram, self.eps)
        active = np.diag(g_hat) >= self.mask_tol
        n = int(active.sum())
        alpha = np.zeros(k)
        iters, gap = 0, 0.0
        if n == 0:
            alpha[:] = 1.0 / k
            return Aggregation(np.zeros(k), alpha, 0, 0.0, float("nan"), active)
        # Bargain over unit directions (the cosine matrix): exactly scale-invariant. eps only enters the
        # applied direction sum_j alpha_j g_j / (||g_j|| + eps), as in the paper.
        norms = np.sqrt(np.diag(gram)[active])
        cosine = gram[np.ix_(active, active)] / np.outer(norms, norms)
        cosine = np.clip(0.5 * (cosine + cosine.T), -1.0, 1.0)
        np.fill_diagonal(cosine, 1.0)
        if n <= 2:
            alpha[active] = 1.0 / n  # closed forms (module docstring)
        else:
            a_sub, iters, gap = frank_wolfe_nash(
                cosine, self._start(k, active), self.iterations, self.eps_nash, self.tol, self.away_steps
            )
            alpha[active] = a_sub
        self._alpha_prev = alpha.copy()
        objective = nash_objective(alpha[active], cosine, self.eps_nash)
        return Aggregation(alpha * scale * active, alpha, iters, gap, objective, active)

    def __repr__(self) -> str:
        return (
            f"NashAggregator(iterations={self.iterations}, eps={self.eps:g}, eps_nash={self.eps_nash:g}, "
            f"warm_start={self.warm_start})"
        )
