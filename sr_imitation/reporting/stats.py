"""Paired tests over training seeds: the statistics the comparisons pre-register (docs/RESULTS.md).

For per-seed values ``a`` and ``b`` of two methods (the same training seeds), the paired differences
``d_s = a_s - b_s`` are tested with

- **Student's paired t-test**: ``t = mean(d) / (sd(d) / sqrt(n))`` with ``n - 1`` degrees of freedom; the p-value
  one-sided (``greater``: H1 says mean(d) > 0) or two-sided. Student's t survival function through the regularized
  incomplete beta function, ``P(T > t) = I_{df / (df + t^2)}(df / 2, 1 / 2) / 2`` for ``t >= 0``, evaluated by its
  continued fraction (Lentz's method); checked against SciPy in the tests. No dependency beyond NumPy.
- **the exact sign-flip permutation test** (Fisher's randomization test of the paired differences): under H0 each
  difference's sign is as likely + as -, so the p-value is the fraction of all ``2^n`` sign assignments whose mean is
  at least as extreme as the observed one (in the tested direction, or in absolute value for two-sided), enumerated
  exactly (no sampling); no normality assumed. Its smallest possible value is ``2^-n`` one-sided (1/32 at 5 seeds,
  1/1024 at 10) and ``2^(1-n)`` two-sided.
- **a bootstrap confidence interval** of mean(d): percentile interval over resamples of the seeds with replacement
  (10,000 resamples, fixed generator seed: the interval is reproducible).

All differences zero gives t = nan and p = 1 (no evidence either way); a constant nonzero difference gives
t = +-inf and p = 0 (one-sided in its direction). Fewer than two pairs: nothing can be tested (t and p are nan).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

ALTERNATIVES = ("greater", "less", "two-sided")


@dataclass(frozen=True)
class PairedTest:
    """The result of :func:`paired_test`."""

    n: int
    mean: float
    sem: float
    t: float
    p: float
    alternative: str
    ci_low: float
    ci_high: float
    ci_level: float
    sign_flip_p: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _betacf(a: float, b: float, x: float, max_iter: int = 300, eps: float = 3e-16) -> float:
    """Continued fraction of the incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, max_iter + 1):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < eps:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """The regularized incomplete beta function I_x(a, b), 0 <= x <= 1."""
    if not 0.0 <= x <= 1.0:
        raise ValueError(f"betainc: x must be in [0, 1], got {x}")
    if x in (0.0, 1.0):
        return x
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b


def t_sf(t: float, df: float) -> float:
    """P(T > t) for Student's t with ``df`` degrees of freedom."""
    if math.isnan(t):
        return float("nan")
    if math.isinf(t):
        return 0.0 if t > 0 else 1.0
    tail = 0.5 * betainc(df / 2.0, 0.5, df / (df + t * t))
    return tail if t >= 0 else 1.0 - tail


def paired_test(a: Sequence[float], b: Sequence[float], alternative: str = "two-sided", ci_level: float = 0.95,
                resamples: int = 10_000, seed: int = 0) -> PairedTest:
    """Paired t-test of ``a - b`` (see the module docstring) with a bootstrap CI of the mean difference."""
    if alternative not in ALTERNATIVES:
        raise ValueError(f"alternative must be one of {ALTERNATIVES}, got {alternative!r}")
    if len(a) != len(b):
        raise ValueError(f"paired values need equal lengths, got {len(a)} and {len(b)}")
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    n = int(d.size)
    nan = float("nan")
    if n < 2:
        return PairedTest(n, float(d.mean()) if n else nan, nan, nan, nan, alternative, nan, nan, ci_level, nan)
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    sem = sd / math.sqrt(n)
    constant = sd <= 1e-12 * max(1.0, abs(mean))  # equal differences up to float rounding
    zero = abs(mean) <= 1e-12
    t = (nan if zero else math.copysign(math.inf, mean)) if constant else mean / sem
    if math.isnan(t):
        p = 1.0
    elif alternative == "greater":
        p = t_sf(t, n - 1)
    elif alternative == "less":
        p = t_sf(-t, n - 1)
    else:
        p = min(1.0, 2.0 * t_sf(abs(t), n - 1))
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, n, size=(resamples, n))].mean(axis=1)
    low, high = np.quantile(means, [(1 - ci_level) / 2, 1 - (1 - ci_level) / 2])
    return PairedTest(n, mean, sem, t, p, alternative, float(low), float(high), ci_level, sign_flip_p(d, alternative))


MAX_SIGN_FLIP_PAIRS = 20
"""Up to 2^20 sign assignments are enumerated exactly (our bound: about a million rows of n numbers)."""


def sign_flip_p(d: Sequence[float], alternative: str = "two-sided") -> float:
    """Exact sign-flip permutation p of the mean of the paired differences ``d`` (module docstring): the fraction of
    the ``2^n`` sign assignments ``s`` with ``mean(s * |d|)`` at least as extreme as ``mean(d)``. Ties within a
    relative 1e-12 count as "at least as extreme" (exact ties occur: equal differences, zeros). NaN for fewer than
    one pair; ``ValueError`` above :data:`MAX_SIGN_FLIP_PAIRS` pairs."""
    if alternative not in ALTERNATIVES:
        raise ValueError(f"alternative must be one of {ALTERNATIVES}, got {alternative!r}")
    values = np.asarray(d, dtype=float)
    n = int(values.size)
    if n == 0:
        return float("nan")
    if n > MAX_SIGN_FLIP_PAIRS:
        raise ValueError(f"sign-flip test: {n} pairs, exact enumeration stops at {MAX_SIGN_FLIP_PAIRS}")
    signs = 1.0 - 2.0 * ((np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1)
    means = signs @ np.abs(values) / n
    observed = float(values.mean())
    tol = 1e-12 * max(1.0, float(np.abs(values).max()))
    if alternative == "greater":
        extreme = means >= observed - tol
    elif alternative == "less":
        extreme = means <= observed + tol
    else:
        extreme = np.abs(means) >= abs(observed) - tol
    return float(extreme.mean())


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm-Bonferroni adjusted p values of one family of tests, in the input order: sorted ascending, the i-th
    smallest (0-based) is multiplied by m - i, made non-decreasing and capped at 1; rejecting where the adjusted p
    is below alpha controls the family-wise error rate at alpha. NaN p values (tests without data) stay NaN and do
    not count in m."""
    finite = [(p, i) for i, p in enumerate(p_values) if not math.isnan(p)]
    out = [float("nan")] * len(p_values)
    running = 0.0
    for rank, (p, i) in enumerate(sorted(finite)):
        running = max(running, min(1.0, (len(finite) - rank) * p))
        out[i] = running
    return out
