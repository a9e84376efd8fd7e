"""Nash-bargained weights on the simplex (paper Eq. 1), solved by warm-started Frank-Wolfe.

Objective, with u = G_hat alpha the agreement of each normalized memory gradient with the combined direction:

    alpha* = argmax_{alpha in simplex} f(alpha),   f(alpha) = sum_i h(u_i),   u = G_hat alpha.

``h`` is ``log(u + eps_nash)`` for u >= 0 (exactly Eq. 1). Eq. 1 is undefined where a memory disagrees with the
combined direction (u < 0, which happens when gradients conflict); there we continue ``h`` by its
second-order Taylor expansion at 0, ``log(eps_nash) + u/eps_nash - u^2/(2 eps_nash^2)``. The extension is
concave and C^2, equals Eq. 1 on every alpha where all memories agree, and penalizes disagreement steeply, so
the solver is well defined for every finite input.

Solver (see ``../shared/notes/nash-bargaining-solver.md`` section 3): Frank-Wolfe with the closed-form linear
oracle (the vertex of the largest partial derivative), away steps (Lacoste-Julien & Jaggi 2015) so that a
vertex can leave the support quickly, an exact line search on the concave 1-D restriction (safeguarded
Newton), and the duality gap as stopping certificate. Exact line search keeps a warm start: a step size is
never forced to 1 at the first iteration as the open-loop rule 2/(t+2) would.

Documented behaviour on degenerate inputs:

* k = 1 (or one non-zero gradient): alpha = [1].
* Zero gradients (``||g_hat_i||^2 < mask_tol``): masked, alpha_i = 0; they would otherwise hold warm-start mass
  that Frank-Wolfe only removes slowly. All gradients zero: alpha uniform, weights 0.
* k = 2 non-zero gradients: alpha = (1/2, 1/2) in closed form. f is symmetric under alpha <-> 1 - alpha for any
  cosine c in [-1, 1] (also with the extension) and concave, so 1/2 is optimal; for c = -1 the direction is 0.
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


def _dh(u: np.ndarray, eps: float) -> np.ndarray:
    return np.where(u >= 0.0, 1.0 / (np.maximum(u, 0.0) + eps), (eps - u) / (eps * eps))


def _d2h(u: np.ndarray, eps: float) -> np.ndarray:
    return np.where(u >= 0.0, -1.0 / (np.maximum(u, 0.0) + eps) ** 2, -1.0 / (eps * eps))


def nash_objective(alpha: np.ndarray, g_hat: np.ndarray, eps_nash: float = NASH_EPS) -> float:
    """f(alpha) of Eq. 1 (with the concave extension for u < 0) for a normalized Gram matrix ``g_hat``."""
    return float(_h(g_hat @ np.asarray(alpha, dtype=np.float64), eps_nash).sum())


def _line_search(u: np.ndarray, delta: np.ndarray, gamma_max: float, eps: float) -> float:
    """argmax over gamma in [0, gamma_max] of sum_i h(u_i + gamma delta_i) (concave): safeguarded Newton."""
    lo, hi = 0.0, gamma_max
    d_hi = float(delta @ _dh(u + hi * delta, eps))
    if d_hi >= 0.0:
        return hi
    gamma = 0.5 * hi
    for _ in range(_NEWTON_MAX_ITERS):
        v = u + gamma * delta
        d1 = float(delta @ _dh(v, eps))
        if d1 > 0.0:
            lo = gamma
        else:
            hi = gamma
        if abs(d1) <= 1e-12 * (1.0 + float(np.abs(delta).sum())) or hi - lo <= 1e-15:
            return gamma
        d2 = float((delta * delta) @ _d2h(v, eps))
        step = gamma - d1 / d2 if d2 < 0.0 else math.nan
        gamma = step if lo < step < hi else 0.5 * (lo + hi)
    return gamma


def frank_wolfe_nash(
    g_hat: np.ndarray,
    alpha0: np.ndarray,
    max_iters: int,
    eps_nash: float = NASH_EPS,
    tol: float = 1e-9,
    away_steps: bool = True,
) -> tuple[np.ndarray, int, float]:
    """Run Frank-Wolfe on Eq. 1 from ``alpha0``; returns ``(alpha, iterations, duality_gap)``.

    Stops after ``max_iters`` iterations or when the duality gap ``max_j grad_j - alpha . grad`` is at most
    ``tol * k`` (``alpha . grad`` is about k near the optimum, so ``tol`` is relative).
    """
    k = g_hat.shape[0]
    alpha = np.asarray(alpha0, dtype=np.float64).copy()
    u = g_hat @ alpha
    gap = math.inf
    it = 0
    for it in range(1, max_iters + 1):
        grad = g_hat @ _dh(u, eps_nash)
        lin = float(alpha @ grad)
        j = int(np.argmax(grad))
        gap = float(grad[j]) - lin
        if gap <= tol * k:
            return alpha, it - 1, gap
        fw_dir_gain = gap
        a = -1
        away_gain = -math.inf
        if away_steps:
            support = np.flatnonzero(alpha > 0.0)
            a = int(support[np.argmin(grad[support])])
            away_gain = lin - float(grad[a])
        if away_gain > fw_dir_gain and alpha[a] < 1.0:
            # Away step: move mass off vertex a, direction alpha - e_a, feasible up to alpha_a / (1 - alpha_a).
            gamma_max = float(alpha[a]) / (1.0 - float(alpha[a]))
            delta = u - g_hat[:, a]
            gamma = _line_search(u, delta, gamma_max, eps_nash)
            alpha *= 1.0 + gamma
            alpha[a] -= gamma
            if gamma >= gamma_max:
                alpha[a] = 0.0  # drop step: remove the vertex exactly
        else:
            delta = g_hat[:, j] - u
            gamma = _line_search(u, delta, 1.0, eps_nash)
            alpha *= 1.0 - gamma
            alpha[j] += gamma
        np.clip(alpha, 0.0, None, out=alpha)
        alpha /= alpha.sum()
        u = g_hat @ alpha
    grad = g_hat @ _dh(u, eps_nash)
    gap = float(grad.max() - alpha @ grad)
    return alpha, it, gap


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
        tol: float = 1e-9,
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
        if n <= 2:
            alpha[active] = 1.0 / n  # closed form for one or two memories (see module docstring)
        else:
            sub = g_hat[np.ix_(active, active)]
            a_sub, iters, gap = frank_wolfe_nash(
                sub, self._start(k, active), self.iterations, self.eps_nash, self.tol, self.away_steps
            )
            alpha[active] = a_sub
        self._alpha_prev = alpha.copy()
        objective = nash_objective(alpha[active], g_hat[np.ix_(active, active)], self.eps_nash)
        return Aggregation(alpha * scale * active, alpha, iters, gap, objective, active)

    def __repr__(self) -> str:
        return (
            f"NashAggregator(iterations={self.iterations}, eps={self.eps:g}, eps_nash={self.eps_nash:g}, "
            f"warm_start={self.warm_start})"
        )
