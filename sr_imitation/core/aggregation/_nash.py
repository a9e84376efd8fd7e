"""Nash-bargained weights on the simplex (paper Eq. 1), solved exactly.

With C the cosine matrix of the memory gradients (the Gram matrix of the unit directions g_hat_i) and
u = C alpha the agreement of each memory with the combined direction d = sum_j alpha_j g_hat_j, Eq. 1 is

    alpha* = argmax_{alpha in simplex} f(alpha),   f(alpha) = sum_i log(u_i + eps_nash),   u = C alpha,

defined where every u_i > -eps_nash. f is concave; ``-f`` is a self-concordant barrier of that set composed with
a linear map, so Newton's method is the natural solver and needs few iterations for the k <= 16 memories of a
sleep phase.

Solver (:func:`solve_nash`), a primal active-set Newton method on the exact Eq. 1 (no continuation below u = 0):

1. Start. The warm start (previous call's alpha) or the uniform point if no memory opposes it (min u >= 0);
   otherwise the min-norm point alpha_mn of the hull (``_min_norm.py``), which opposes no memory
   (u_i >= ||d_mn||^2 >= 0). Both lie in the domain of Eq. 1.
2. Iterate, on the support S of alpha: the equality-constrained Newton step p on the face (Hessian
   -C_S^T diag(1/(u+eps)^2) C_S, Jacobi-scaled and regularized by 1e-12), damped by 1/(1 + lambda) while the
   Newton decrement lambda >= 1/4 (the self-concordant damping, which keeps every u_i + eps > 0), a ratio test
   that drops a vertex the step would make negative, and a backtracking safeguard (never leave the domain, never
   lower f); when a vertex outside the face has the largest partial derivative and the face is nearly optimal,
   that vertex enters by a Frank-Wolfe step with an exact line search.
3. Stop when the Frank-Wolfe duality gap ``max_j grad_j - alpha.grad`` (an upper bound on f* - f) is at most
   ``tol * max(1, |f|)``: the returned objective is within ``tol`` relative of the maximum (default 1e-9).

When no direction agrees with every memory. If some direction agrees with every memory with margin
tau = min_i u_i > (k - 1) eps_nash, the maximizer of Eq. 1 has every u_i > 0: at a point with u_i <= 0, moving
toward that direction raises f at rate >= tau/eps_nash - (k - 1) > 0. Otherwise the memories are (nearly)
Pareto-stationary: 0 lies in (or very near) the convex hull of the unit gradients and, by Gordan's alternative,
every direction opposes some memory to first order (or only directions orthogonal to the conflicting ones do
not). Eq. 1 then still has a maximizer, but it sits where some u_i is within eps_nash of 0 and is decided by the
value of eps_nash. Our rule (our choice; the paper does not discuss it): **return the maximizer of Eq. 1 when it
opposes no memory (every u_i >= 0), else the min-norm point** alpha_mn, MGDA's Pareto-stationary direction
(d_mn = 0 when 0 is in the hull): it raises no memory's loss to first order, so the sleep step then reduces to
the anchor term. Example: for gradients (g, -g, h) with h orthogonal to g the maximizer is alpha = (0, 0, 1),
d = h (u = (0, 0, 1)), which is returned; for three unit vectors at 120 degrees it is the uniform point, d = 0.
So the default solver never returns a direction that opposes a memory (u_i >= -1e-12).

Normalization. The paper normalizes g_hat_i = g_i / (||g_i|| + eps). We bargain on the exact unit directions (the
cosine matrix, zero gradients masked), so the weights are exactly invariant to rescaling any gradient, and apply
the paper's g_hat in the combined direction d = sum_j alpha_j g_j / (||g_j|| + eps). The two differ only for
gradients with norm comparable to eps.

Documented behaviour on degenerate inputs:

* k = 1 (or one non-zero gradient): alpha = [1].
* Zero gradients (``||g_hat_i||^2 < mask_tol``): masked, alpha_i = 0. All gradients zero: weights 0.
* k = 2 non-zero gradients: alpha = (1/2, 1/2) in closed form (f is symmetric under alpha <-> 1 - alpha on unit
  directions and concave); for c = -1 that is also the min-norm point, d = 0.
* Identical gradients: f is constant; the start is returned unchanged (any alpha is optimal).
* Non-finite Gram entries: ``ValueError`` naming the rows; the sleep loop checks before calling and skips.

The paper's warm-started Frank-Wolfe with a fixed small number of iterations is kept as the ``nash_fw``
aggregator (``_frank_wolfe.py``) for the ablation; it is approximate and, under conflicts, can return weights
with negative agreement (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from operator import mul
from typing import Any

import numpy as np

from sr_imitation.core.aggregation._base import Aggregation, Aggregator
from sr_imitation.core.aggregation._gram import GRAD_NORM_EPS, as_gram, cosine_matrix, gradient_norms
from sr_imitation.core.aggregation._min_norm import _REG, min_norm_point

NASH_EPS = 1e-5
"""Floor eps_Nash of Eq. 1. The paper gives no value; we use the gradient-normalization constant."""

try:  # numpy's LAPACK gufunc without np.linalg.solve's Python-level checks (~4x less overhead for k <= 16)
    from numpy.linalg import _umath_linalg

    def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return _umath_linalg.solve(a, b, signature="dd->d")
except ImportError:  # pragma: no cover - other numpy layouts
    _solve = np.linalg.solve

STALL_TOL = 1e-6
"""When f stops increasing (round-off), the solve still counts as optimal if the gap is within this relative
tolerance (the accuracy the exact solver promises); otherwise its status is ``stalled``."""

AGREEMENT_TOL = 1e-12
"""Agreement u_i below -AGREEMENT_TOL counts as opposing the memory (round-off level for unit vectors)."""


def nash_objective(alpha: np.ndarray, cosine: np.ndarray, eps_nash: float = NASH_EPS) -> float:
    """f(alpha) of Eq. 1 for a cosine (unit-direction Gram) matrix; ``-inf`` outside its domain (some u_i <= -eps)."""
    u = np.asarray(cosine, dtype=np.float64) @ np.asarray(alpha, dtype=np.float64)
    if not (u + eps_nash > 0.0).all():
        return -math.inf
    return float(np.log(u + eps_nash).sum())


@dataclass(frozen=True)
class NashSolution:
    """Result of :func:`solve_nash`.

    Attributes:
        alpha: weights on the unit directions (on the simplex).
        iterations: Newton / Frank-Wolfe steps taken (plus the min-norm solver's when it ran).
        gap: the Frank-Wolfe duality gap at return (an upper bound on f* - f; 0 for closed forms and the
            Pareto-stationary answer).
        status: ``optimal`` (gap within tolerance), ``pareto_stationary`` (the maximizer opposed some memory: the
            min-norm point is returned), ``max_iterations`` (budget exhausted; alpha is feasible and better than
            the start),
            ``stalled`` (f stopped increasing at round-off level with a gap above 1e-6 relative).
        min_agreement: min_i u_i at alpha.
        objective: f(alpha) of Eq. 1 (``-inf`` outside its domain).
    """

    alpha: np.ndarray
    iterations: int
    gap: float
    status: str
    min_agreement: float
    objective: float


def _log_line_search(s: np.ndarray, delta: np.ndarray, gamma_max: float) -> float:
    """argmax over gamma in [0, gamma_max] of sum_i log(s_i + gamma delta_i), from inside the domain (s_i > 0).

    Safeguarded Newton on the derivative, which decreases monotonically (concavity); the domain boundary, where
    the objective falls to -inf, is never reached.
    """
    hi, open_hi = gamma_max, False
    neg = delta < 0.0
    if neg.any():
        dom = float((s[neg] / -delta[neg]).min())
        if dom <= hi:
            hi, open_hi = dom, True
    if not open_hi and float((delta / (s + hi * delta)).sum()) >= 0.0:
        return hi
    lo, gamma = 0.0, 0.0
    for _ in range(100):
        w = delta / (s + gamma * delta)
        d1 = float(w.sum())
        d2 = -float(w @ w)
        if d1 > 0.0:
            lo = gamma
        else:
            hi = gamma
        step = gamma - d1 / d2 if d2 < 0.0 else -1.0
        if not lo < step < hi:
            step = 0.5 * (lo + hi)
        if abs(step - gamma) <= 1e-15 * gamma_max or hi - lo <= 1e-15 * gamma_max:
            return max(lo, min(step, hi))
        gamma = step
    return lo


def _newton(c: np.ndarray, alpha: np.ndarray, eps: float, tol: float, max_iterations: int
            ) -> tuple[np.ndarray, int, float, str, float]:
    """The active-set Newton iteration of the module docstring from a start with every u_i > 0.

    Returns ``(alpha, steps, gap, status, f)``. Written with as few numpy calls per step as possible, reductions
    on Python lists: for k <= 16 the per-call overhead, not the O(k^3) arithmetic, is the cost.
    """
    n = c.shape[0]
    rng = range(n)
    u = c @ alpha
    f = math.fsum(np.log(u + eps).tolist())
    gap = math.inf
    stalls = 0
    for it in range(1, max_iterations + 1):
        r = 1.0 / (u + eps)
        grad = c @ r
        gl, al = grad.tolist(), alpha.tolist()
        lin = math.fsum(map(mul, al, gl))
        j = max(rng, key=gl.__getitem__)  # first index on ties: deterministic
        gap = gl[j] - lin
        if gap <= tol * max(1.0, abs(f)):
            return alpha, it - 1, max(gap, 0.0), "optimal", f
        if stalls >= 2:  # round-off floor (u_i ~ 0 makes grad ~ 1/eps^2 * 1e-16): f no longer increases
            return alpha, it - 1, gap, "optimal" if gap <= STALL_TOL * max(1.0, abs(f)) else "stalled", f
        idx = [i for i in rng if al[i] > 0.0]
        drop = -1
        if al[j] == 0.0 and gap > max(gl[i] for i in idx) - lin:
            # Add vertex j: Frank-Wolfe step toward e_j with an exact line search on the true Eq. 1.
            gamma = _log_line_search(u + eps, c[j] - u, 1.0)
            alpha = alpha * (1.0 - gamma)
            alpha[j] += gamma
        else:
            # Newton step on the face: max g.p - p^T M p / 2 s.t. sum(p) = 0, M = C_S^T diag(r^2) C_S (the negative
            # Hessian of Eq. 1 on the face), slightly regularized (``_REG``).
            m = len(idx)
            cs = c[:, idx] if m < n else c
            cw = cs * r[:, None]
            mat = cw.T @ cw
            # Jacobi scaling (diag(M) spans 1..1/eps^2 when some u_i ~ 0), then a relative Tikhonov term.
            sc = 1.0 / np.sqrt(mat.diagonal())
            mat *= np.multiply.outer(sc, sc)
            mat.flat[:: m + 1] += _REG
            rhs = np.empty((m, 2))
            rhs[:, 0] = grad[idx] if m < n else grad
            rhs[:, 1] = 1.0
            rhs *= sc[:, None]
            sol = _solve(mat, rhs)
            sol *= sc[:, None]
            x, y = sol.T.tolist()
            nu = math.fsum(x) / math.fsum(y)
            pl = [xa - nu * ya for xa, ya in zip(x, y, strict=True)]
            decrement = math.sqrt(max(math.fsum(gl[a] * pa for a, pa in zip(idx, pl, strict=True)), 0.0))
            t = 1.0 if decrement < 0.25 else 1.0 / (1.0 + decrement)
            for a, pa in zip(idx, pl, strict=True):
                if pa < 0.0 and al[a] / -pa <= t:
                    t, drop = al[a] / -pa, a
            p = np.array(pl)
            w = cs @ p
            for _ in range(60):  # safeguard: stay in the domain and never decrease f
                s_new = (u + eps + t * w).tolist()
                if min(s_new) > 0.0 and math.fsum(map(math.log, s_new)) >= f - 1e-12 * abs(f):
                    break
                t *= 0.5
                drop = -1
            alpha = alpha.copy()
            alpha[idx] = np.maximum(alpha[idx] + t * p, 0.0)
        if drop >= 0:
            alpha[drop] = 0.0
        alpha /= math.fsum(alpha.tolist())
        u = c @ alpha
        f_new = math.fsum(np.log(u + eps).tolist())
        stalls = stalls + 1 if f_new - f <= 1e-15 * max(1.0, abs(f)) else 0
        f = f_new
    return alpha, max_iterations, max(gap, 0.0), "max_iterations", f


def solve_nash(
    cosine: np.ndarray,
    alpha0: np.ndarray | None = None,
    eps_nash: float = NASH_EPS,
    tol: float = 1e-9,
    max_iterations: int = 100,
) -> NashSolution:
    """Maximize Eq. 1 over the simplex for a cosine matrix (unit diagonal); see the module docstring.

    Args:
        cosine: n x n cosine matrix of the (non-zero) memory gradients.
        alpha0: warm start on the simplex (ignored when it does not agree with every memory); default uniform.
        eps_nash: the floor of Eq. 1.
        tol: relative duality-gap tolerance.
        max_iterations: Newton / Frank-Wolfe steps per call.
    """
    c = np.asarray(cosine, dtype=np.float64)
    n = c.shape[0]
    if n == 1:
        return NashSolution(np.ones(1), 0, 0.0, "optimal", float(c[0, 0]), math.log(float(c[0, 0]) + eps_nash))
    alpha = np.full(n, 1.0 / n) if alpha0 is None else np.array(alpha0, dtype=np.float64)
    iters = 0
    if min((c @ alpha).tolist()) < 0.0:
        alpha, iters = min_norm_point(c)  # agrees with every memory (u_i >= ||d_mn||^2 >= 0)
    alpha, steps, gap, status, f = _newton(c, alpha, eps_nash, tol, max_iterations)
    iters += steps
    u_min = min((c @ alpha).tolist())
    if u_min < -AGREEMENT_TOL:
        # The maximizer opposes some memory: only possible when 0 is in (or within (k - 1) eps_nash of) the hull.
        alpha, extra = min_norm_point(c)
        return NashSolution(alpha, iters + extra, 0.0, "pareto_stationary", float((c @ alpha).min()),
                            nash_objective(alpha, c, eps_nash))
    return NashSolution(alpha, iters, gap, status, u_min, f)


class NashAggregator(Aggregator):
    """Nash bargaining over normalized memory gradients (Eq. 1), solved exactly, warm-started across calls.

    Args:
        eps: gradient-normalization constant (paper: 1e-5).
        eps_nash: the floor eps_Nash of Eq. 1.
        tol: relative duality-gap tolerance (the objective is within ``tol`` relative of the maximum).
        max_iterations: Newton / Frank-Wolfe steps per call (a budget, not a setting of the method: the solver
            stops at the tolerance, typically after 1-3 steps warm and 3-15 cold for k <= 16).
        warm_start: start each solve from the previous call's alpha (paper: enabled).
        mask_tol: memories with ``||g_hat_i||^2`` below this are treated as zero gradients.

    .. note:: The aggregator is stateful (warm start); call :meth:`reset` between sleep phases when the
       memory set changes. A change in k resets it automatically.
    """

    name = "nash"

    def __init__(
        self,
        eps: float = GRAD_NORM_EPS,
        eps_nash: float = NASH_EPS,
        tol: float = 1e-9,
        max_iterations: int = 100,
        warm_start: bool = True,
        mask_tol: float = 1e-6,
    ) -> None:
        super().__init__(eps)
        if max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
        if not eps_nash > 0:
            raise ValueError(f"eps_nash must be > 0, got {eps_nash}")
        if not tol >= 0:
            raise ValueError(f"tol must be >= 0, got {tol}")
        self.eps_nash = float(eps_nash)
        self.tol = float(tol)
        self.max_iterations = int(max_iterations)
        self.warm_start = warm_start
        self.mask_tol = float(mask_tol)
        self._alpha_prev: np.ndarray | None = None

    def reset(self) -> None:
        self._alpha_prev = None

    def state(self) -> dict[str, Any]:
        """The warm start: the previous call's alpha (None before the first call or after :meth:`reset`)."""
        return {"alpha_prev": None if self._alpha_prev is None else self._alpha_prev.tolist()}

    def load_state(self, state: dict[str, Any]) -> None:
        prev = state["alpha_prev"]
        self._alpha_prev = None if prev is None else np.asarray(prev, dtype=np.float64)

    def _start(self, k: int, active: np.ndarray) -> np.ndarray | None:
        prev = self._alpha_prev
        if self.warm_start and prev is not None and prev.shape == (k,):
            start = prev[active]
            if start.sum() > 0.0 and np.isfinite(start).all():
                return start / start.sum()
        return None

    def _solve(self, cosine: np.ndarray, start: np.ndarray | None) -> tuple[np.ndarray, int, float, str, float]:
        sol = solve_nash(cosine, start, self.eps_nash, self.tol, self.max_iterations)
        return sol.alpha, sol.iterations, sol.gap, sol.status, sol.objective

    def _closed_form_objective(self, cosine: np.ndarray) -> float:
        if cosine.shape[0] == 1:
            return math.log(1.0 + self.eps_nash)
        u = 0.5 * (1.0 + float(cosine[0, 1]))
        return 2.0 * math.log(u + self.eps_nash)

    def __call__(self, gram: np.ndarray) -> Aggregation:
        gram = as_gram(gram)
        k = gram.shape[0]
        norms = gradient_norms(gram)
        scale = 1.0 / (norms + self.eps)
        unit = norms * scale
        active = unit * unit >= self.mask_tol  # ||g_hat_i||^2 >= mask_tol
        n = int(np.count_nonzero(active))
        alpha = np.zeros(k)
        if n == 0:
            alpha[:] = 1.0 / k
            return Aggregation(np.zeros(k), alpha, 0, 0.0, float("nan"), active, "all_zero")
        # Bargain over unit directions (the cosine matrix): exactly scale-invariant. eps only enters the
        # applied direction sum_j alpha_j g_j / (||g_j|| + eps), as in the paper.
        cosine = cosine_matrix(gram, active, norms)
        iters, gap, status = 0, 0.0, "closed_form"
        if n <= 2:
            alpha[active] = 1.0 / n  # closed forms (module docstring)
            objective = self._closed_form_objective(cosine)
        else:
            alpha[active], iters, gap, status, objective = self._solve(cosine, self._start(k, active))
        self._alpha_prev = alpha
        weights = alpha * scale
        weights[~active] = 0.0
        return Aggregation(weights, alpha.copy(), iters, gap, objective, active, status)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(eps={self.eps:g}, eps_nash={self.eps_nash:g}, tol={self.tol:g}, "
            f"max_iterations={self.max_iterations}, warm_start={self.warm_start})"
        )
