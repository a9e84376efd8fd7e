"""Nash solver benchmark: exactness on conflicting memories, and solve time next to Nash-MTL's CCP.

    python -m sr_imitation.benchmarks.nash [--instances=200] [--calls=200] [--output=outputs/benchmarks/nash.json]

1. **Exactness** (conflicting gradients): random unit gradients, k = 3..5 in 3..7 dimensions, one memory opposing the
   mean of the others, kept when an LP finds a simplex point where every memory agrees with margin >= 1e-3. For
   each solver: instances with some negative agreement u_i < 0, and instances whose Eq. 1 objective is more than
   1e-3 (and 1e-6 relative) below the reference maximizer (SciPy SLSQP with the agreement constraints
   u >= 0, started from the LP's feasible point; the better of it and the exact solver is the reference).
2. **Time per call** for k = 2..16 on Gaussian gradients (256-d): the exact solver cold (uniform start) and warm
   (a sequence of perturbed Gram matrices, warm-started from the previous call, as in a sleep phase), the paper's
   Frank-Wolfe at 5 and 50 iterations, and Nash-MTL's published solver (Navon et al. 2022): the concave-convex
   procedure, up to 20 convex problems solved by cvxpy + ECOS, each re-linearizing the concave part at the
   previous alpha, stopped when ||G alpha - 1/alpha|| < 1e-3 or alpha moves less than 1e-6. The CCP needs the
   optional ``cvxpy`` and ``ecos`` packages (``pip install cvxpy==1.9.3 ecos==2.0.14``); without them its
   column is left out. All numbers come from one process, so the ratios are measured in one run.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sr_imitation.core.aggregation import FrankWolfeNashAggregator, NashAggregator, nash_objective
from sr_imitation.infra.cli_errors import run_cli, setup_logging
from sr_imitation.infra.cli_parsing import parse_command

logger = logging.getLogger(__name__)
PROG = "python -m sr_imitation.benchmarks.nash"
"""The command as a user types it (usage errors and ``--help`` name it)."""


@dataclass
class NashBenchConfig:
    instances: int = 200
    """Conflicting instances (with an agreeing direction) in the exactness check."""
    calls: int = 200
    """Solver calls per timing cell (median reported)."""
    ccp_calls: int = 20
    """CCP calls per timing cell (it is ~100x slower)."""
    ks: tuple[int, ...] = (2, 3, 4, 5, 6, 8, 10, 12, 14, 16)
    """Numbers of memories timed."""
    seed: int = 0
    output: str = "outputs/benchmarks/nash.json"


def conflict_family(rng: np.random.Generator, count: int, margin: float = 1e-3) -> list[np.ndarray]:
    """Cosine matrices of the conflicting family: k = 3..5 unit gradients in 3..7 dims, one opposing the others,
    kept when some simplex point gives every memory agreement >= ``margin`` (checked by an LP)."""
    out = []
    while len(out) < count:
        k, d = int(rng.integers(3, 6)), int(rng.integers(3, 8))
        g = rng.normal(size=(k, d))
        g[0] = -g[1:].mean(axis=0) + 0.5 * rng.normal(size=d)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        c = g @ g.T
        if agreement_margin(c)[0] >= margin:
            out.append(c)
    return out


def agreement_margin(c: np.ndarray) -> tuple[float, np.ndarray]:
    """max over the simplex of min_i (C alpha)_i, and its maximizer (an LP; SciPy)."""
    from scipy.optimize import linprog

    k = c.shape[0]
    res = linprog(np.r_[np.zeros(k), -1.0], A_ub=np.c_[-c, np.ones(k)], b_ub=np.zeros(k),
                  A_eq=np.r_[np.ones(k), 0.0][None], b_eq=[1.0], bounds=[(0, None)] * k + [(None, None)])
    return float(-res.fun), np.clip(res.x[:k], 0.0, None) / np.clip(res.x[:k], 0.0, None).sum()


def scipy_reference(c: np.ndarray, start: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Independent reference: SLSQP on Eq. 1 with the agreement constraints C alpha >= 0, from ``start``."""
    from scipy.optimize import minimize

    k = c.shape[0]
    res = minimize(lambda a: -np.log(np.maximum(c @ a, -eps / 2) + eps).sum(), start,
                   jac=lambda a: -c @ (1.0 / (np.maximum(c @ a, -eps / 2) + eps)), method="SLSQP",
                   bounds=[(0.0, 1.0)] * k,
                   constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1.0, "jac": lambda a: np.ones(k)},
                                {"type": "ineq", "fun": lambda a: c @ a, "jac": lambda a: c}],
                   options={"maxiter": 2000, "ftol": 1e-15})
    alpha = np.clip(res.x, 0.0, None)
    return alpha / alpha.sum()


class CCPNashMTL:
    """Nash-MTL's solver (Navon et al. 2022, section 3; our re-implementation from the paper and the notes in
    ``../shared/notes/nash-bargaining-solver.md`` section 1, for timing only): find alpha > 0 with
    alpha_i (G alpha)_i = 1 by the concave-convex procedure. Each step minimizes
    sum(G alpha) + phi_lin(alpha) / nf subject to -log(alpha_i nf) - log((G alpha)_i) <= 0, phi linearized at the
    previous alpha, G normalized by its Frobenius norm nf; up to 20 steps, ECOS, problem built once per k."""

    def __init__(self, k: int, iterations: int = 20) -> None:
        import cvxpy as cp

        self.cp = cp
        self.k, self.iterations = k, iterations
        self.alpha = cp.Variable(k, nonneg=True)
        self.prev = cp.Parameter(k, value=np.ones(k))
        self.gram = cp.Parameter((k, k), value=np.eye(k))
        self.nf = cp.Parameter(1, value=np.ones(1))
        g_alpha = self.gram @ self.alpha
        g_prev = self.gram @ self.prev
        slope = 1.0 / self.prev + (1.0 / g_prev) @ self.gram
        phi = slope @ (self.alpha - self.prev)
        cons = [-cp.log(self.alpha[i] * self.nf) - cp.log(g_alpha[i]) <= 0 for i in range(k)]
        self.problem = cp.Problem(cp.Minimize(cp.sum(g_alpha) + phi / self.nf), cons)

    def __call__(self, gram: np.ndarray) -> np.ndarray:
        nf = float(np.linalg.norm(gram))
        g = gram / nf
        self.gram.value, self.nf.value = g, np.array([nf])
        alpha = np.ones(self.k)
        for _ in range(self.iterations):
            self.prev.value = alpha
            try:
                self.problem.solve(solver=self.cp.ECOS, warm_start=True, max_iters=100)
            except self.cp.SolverError:
                break
            if self.alpha.value is None:
                break
            new = np.asarray(self.alpha.value)
            done = np.linalg.norm(g @ new - 1.0 / np.maximum(new, 1e-12)) < 1e-3 or np.linalg.norm(new - alpha) < 1e-6
            alpha = new
            if done:
                break
        return alpha


def _median_ms(fn, inputs) -> float:
    times = []
    for x in inputs:
        t0 = time.perf_counter()
        fn(x)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def exactness(cfg: NashBenchConfig) -> dict:
    rng = np.random.default_rng(cfg.seed)
    family = conflict_family(rng, cfg.instances)
    solvers = {
        "nash (exact)": lambda c: NashAggregator(warm_start=False)(c).alpha,
        "nash_fw 50 it": lambda c: FrankWolfeNashAggregator(iterations=50, warm_start=False)(c).alpha,
        "nash_fw 5 it": lambda c: FrankWolfeNashAggregator(iterations=5, warm_start=False)(c).alpha,
    }
    rows = {name: {"negative_agreement": 0, "below_1e-3": 0, "below_1e-6_rel": 0} for name in solvers}
    for i, c in enumerate(family):
        alphas = {name: fn(c) for name, fn in solvers.items()}
        ref_alpha = scipy_reference(c, agreement_margin(c)[1])
        ref = max(nash_objective(ref_alpha, c), nash_objective(alphas["nash (exact)"], c))
        for name, alpha in alphas.items():
            f = nash_objective(alpha, c)
            rows[name]["negative_agreement"] += int((c @ alpha).min() < 0.0)
            rows[name]["below_1e-3"] += int(f < ref - 1e-3)
            rows[name]["below_1e-6_rel"] += int(f < ref - 1e-6 * abs(ref))
        if (i + 1) % 50 == 0:
            logger.info("exactness: %d/%d instances", i + 1, len(family))
    return {"instances": len(family), "solvers": rows}


def timings(cfg: NashBenchConfig) -> dict:
    rng = np.random.default_rng(cfg.seed + 1)
    try:
        import cvxpy  # noqa: F401
        import ecos  # noqa: F401

        have_ccp = True
    except ImportError:
        have_ccp = False
        logger.warning("cvxpy/ecos not installed: the CCP column is left out (pip install cvxpy ecos)")
    out = {}
    for k in cfg.ks:
        jacs = [rng.normal(size=(k, 256)) for _ in range(cfg.calls)]
        grams = [j @ j.T for j in jacs]
        base = rng.normal(size=(k, 256))
        seq = [(base + 0.1 * rng.normal(size=base.shape)) for _ in range(cfg.calls)]
        seq_grams = [j @ j.T for j in seq]
        row = {
            "exact_cold_ms": _median_ms(NashAggregator(warm_start=False), grams),
            "exact_warm_ms": _median_ms(NashAggregator(), seq_grams),
            "fw5_warm_ms": _median_ms(FrankWolfeNashAggregator(iterations=5), seq_grams),
            "fw50_warm_ms": _median_ms(FrankWolfeNashAggregator(iterations=50), seq_grams),
        }
        iters = [NashAggregator(warm_start=False)(g).iterations for g in grams[:50]]
        row["exact_cold_iterations_mean"] = float(np.mean(iters))
        if have_ccp:
            ccp = CCPNashMTL(k)
            ccp(grams[0])  # compile once outside the timing
            row["ccp_ms"] = _median_ms(ccp, grams[: cfg.ccp_calls])
            row["ccp_over_exact_cold"] = row["ccp_ms"] / row["exact_cold_ms"]
            row["ccp_over_exact_warm"] = row["ccp_ms"] / row["exact_warm_ms"]
        out[str(k)] = row
        logger.info("k=%d: %s", k, {key: round(v, 4) for key, v in row.items()})
    return out


def main(cfg: NashBenchConfig) -> dict:
    setup_logging()
    result = {"exactness": exactness(cfg), "timing": timings(cfg), "config": cfg.__dict__}
    path = Path(cfg.output)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2, default=list))
    lines = ["| solver | negative agreement | objective < max - 1e-3 | < max - 1e-6 rel |", "|---|---|---|---|"]
    n = result["exactness"]["instances"]
    for name, r in result["exactness"]["solvers"].items():
        lines.append(f"| {name} | {r['negative_agreement']}/{n} | {r['below_1e-3']}/{n} | {r['below_1e-6_rel']}/{n} |")
    lines += ["", "| k | exact cold ms | exact warm ms | FW-5 warm ms | FW-50 warm ms | CCP ms | CCP / exact cold |"
              " CCP / exact warm |", "|---|---|---|---|---|---|---|---|"]
    for k, r in result["timing"].items():
        ccp = (f"{r['ccp_ms']:.2f} | {r['ccp_over_exact_cold']:.0f}x | {r['ccp_over_exact_warm']:.0f}x"
               if "ccp_ms" in r else "- | - | -")
        lines.append(f"| {k} | {r['exact_cold_ms']:.3f} | {r['exact_warm_ms']:.3f} | {r['fw5_warm_ms']:.3f} | "
                     f"{r['fw50_warm_ms']:.3f} | {ccp} |")
    print("\n".join(lines))  # noqa: T201
    return result


if __name__ == "__main__":
    run_cli(PROG, lambda args: main(parse_command(NashBenchConfig, args, prog=PROG)))  # usage errors: one line
