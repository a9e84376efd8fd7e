"""The min-norm point of the convex hull of unit memory gradients (MGDA; Desideri 2012, Sener & Koltun 2018).

    alpha_mn = argmin_{alpha in simplex} alpha^T C alpha,   d_mn = sum_j alpha_mn_j g_hat_j,
    ||d_mn||^2 = alpha_mn^T C alpha_mn,

with C the cosine (unit-direction Gram) matrix. Its optimality conditions say ``(C alpha_mn)_i >= ||d_mn||^2`` for
every memory i, so d_mn *agrees* with every memory (u_i = <g_hat_i, d_mn> >= ||d_mn||^2 >= 0). Two consequences
the Nash solver uses (``_nash.py``):

* an agreeing direction (all u_i > 0) exists if and only if ``d_mn != 0`` (Gordan's alternative: otherwise 0 lies
  in the convex hull of the g_hat_i and every direction opposes some memory to first order);
* alpha_mn is a feasible start for Eq. 1 whenever one exists.

Solved exactly by a primal active-set method (Wolfe's min-norm-point idea): on the current support the
equality-constrained quadratic is minimized by one linear solve, a ratio test drops a vertex the step would make
negative, and when the support is optimal the most violated vertex is added by an exact Frank-Wolfe (MGDA) step.
Every step lowers the objective, so no support repeats and the loop ends after finitely many steps.
"""

from __future__ import annotations

import numpy as np

_REG = 1e-12
"""Relative Tikhonov term on the face systems (our choice): rank-deficient C (more memories than gradient
dimensions) makes a face's system singular; any solution is then optimal and the regularized one is picked."""


def face_step(m: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Solve ``max g.p - p^T m p / 2  s.t.  sum(p) = 0`` (m PSD): the Newton step on a face of the simplex.

    Returns ``p = x - nu y`` with ``m x = g``, ``m y = 1`` and ``nu`` chosen so that ``sum(p) = 0``.
    """
    n = m.shape[0]
    reg = _REG * max(float(np.trace(m)) / n, 1e-300)
    rhs = np.empty((n, 2))
    rhs[:, 0] = g
    rhs[:, 1] = 1.0
    sol = np.linalg.solve(m + reg * np.eye(n), rhs)
    x, y = sol[:, 0], sol[:, 1]
    return x - (x.sum() / y.sum()) * y


def min_norm_point(c: np.ndarray, tol: float = 1e-14, max_iterations: int = 200) -> tuple[np.ndarray, int]:
    """``(alpha_mn, iterations)``: the min-norm point of the hull of unit gradients with cosine matrix ``c``.

    Stops when the Frank-Wolfe gap ``alpha.q - min_j q_j`` (q = C alpha; an upper bound on the objective's distance
    to its minimum) is at most ``tol``.
    """
    n = c.shape[0]
    alpha = np.full(n, 1.0 / n)
    it = 0
    for it in range(1, max_iterations + 1):
        q = c @ alpha
        v = float(alpha @ q)
        support = alpha > 0.0
        j = int(np.argmin(q))
        out_gap = v - float(q[j])
        face_gap = float(q[support].max()) - v
        if max(out_gap, face_gap) <= tol:
            return alpha, it - 1
        if out_gap > face_gap and not support[j]:
            # Exact MGDA step toward vertex j: minimize ||d + gamma (g_hat_j - d)||^2 over gamma in [0, 1].
            denom = v - 2.0 * float(q[j]) + float(c[j, j])
            gamma = 1.0 if denom <= 0.0 else min(1.0, out_gap / denom)
            alpha *= 1.0 - gamma
            alpha[j] += gamma
            continue
        idx = np.flatnonzero(support)
        p = face_step(c[np.ix_(idx, idx)], -q[idx])
        a = alpha[idx]
        neg = p < 0.0
        t, drop = 1.0, -1
        if neg.any():
            ratios = a[neg] / -p[neg]
            r = int(np.argmin(ratios))
            if ratios[r] < 1.0:
                t, drop = float(ratios[r]), int(idx[np.flatnonzero(neg)[r]])
        alpha[idx] = np.maximum(a + t * p, 0.0)
        if drop >= 0:
            alpha[drop] = 0.0
        alpha /= alpha.sum()
    return alpha, it
