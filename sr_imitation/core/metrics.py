"""Continual-learning metrics of the paper (Eqs. 4-5 and Appendix): AFSR, PRS, BWT, SPI.

Conventions. Skills are learned in stream order 1..K. The success matrix ``S`` is K x K with ``S[k, i]`` the
success rate on skill i measured after training through skill k (0-based in code), NaN for i > k (not yet
learned). All ``*_curve`` functions return one value per stage k (NaN where undefined).

* AFSR_k = (1/k) sum_{i<=k} S[k, i]                                            (Eq. 4)
* PRS_k  = (1/|C_k|) sum_{(i,j) in C_k} min(S[k, i], S[k, j]),                 (Eq. 5)
  C_k = the pre-registered pairs whose two skills are both learned by stage k; PRS is defined for k >= 2 and
  is NaN while no pair is complete.
* BWT_k  = (1/(k-1)) sum_{i<k} (S[k, i] - S[i, i])  for k >= 2 (GEM sign: negative = forgetting).
* SPI (Synergy Preservation Index): for skill i let X_i^ref be the observation-space trajectories of the policy
  right after skill i was learned (stage i) and X_i^(k) those of the policy after stage k, stacked over
  evaluation episodes (T x d). With U = top-3 principal directions (d x 3, orthonormal) of the mean-centred
  rows,

      SPI_i^(k) = ||U_ref^T U_k||_F^2 / 3  =  mean squared cosine of the 3 principal angles,  in [0, 1],
      SPI_k     = (1/(k-1)) sum_{i<k} SPI_i^(k)   for k >= 2.

  SPI = 1 means the skill's top-3 trajectory subspace is unchanged, 0 that it became orthogonal. (The paper
  defines SPI only in words, "preservation of the top-three PCA directions of the reference observation-space
  trajectory"; this is our exact reading.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

MT5_SKILLS: tuple[str, ...] = ("reach", "door-open", "drawer-open", "window-close", "button-press-topdown")
"""Meta-World MT5 stream order (Appendix A.1, "Skill stream")."""

MT5_PAIRS: tuple[tuple[str, str], ...] = (
    ("reach", "door-open"),
    ("door-open", "drawer-open"),
    ("reach", "drawer-open"),
    ("door-open", "window-close"),
    ("drawer-open", "button-press-topdown"),
    ("window-close", "button-press-topdown"),
)
"""The six pre-registered MT5 PRS pairs (Appendix A.1, "Evaluation protocol")."""

SURGICAI_SKILLS: tuple[str, ...] = ("approach", "place", "insert", "regrasp", "pullout")
"""SurgicAI stream order (Appendix A.2, "Skill stream")."""

SURGICAI_PAIRS: tuple[tuple[str, str], ...] = (
    ("approach", "place"),
    ("place", "insert"),
    ("insert", "regrasp"),
    ("regrasp", "pullout"),
    ("approach", "insert"),
    ("place", "regrasp"),
    ("insert", "pullout"),
)
"""The seven pre-registered workflow-ordered SurgicAI PRS pairs (Appendix A.2, "Evaluation protocol")."""

SPI_COMPONENTS = 3


def canonical_skill(name: str) -> str:
    """Strip a Meta-World version suffix ("door-open-v3" -> "door-open") so pairs match by skill identity."""
    for suffix in ("-v1", "-v2", "-v3"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def all_pairs(skills: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """Every unordered pair (the MT8 protocol: all C(8, 2) = 28 pairs)."""
    return tuple((a, b) for i, a in enumerate(skills) for b in skills[i + 1 :])


def as_success_matrix(matrix: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """Validate a K x K success matrix: rates in [0, 1] on and below the diagonal, NaN allowed above.

    Raises:
        ValueError: wrong shape, values outside [0, 1], or missing (NaN) entries on/below the diagonal.
    """
    s = np.array(matrix, dtype=np.float64)
    if s.ndim != 2 or s.shape[0] != s.shape[1] or s.shape[0] == 0:
        raise ValueError(f"success matrix must be a non-empty K x K array, got shape {s.shape}")
    lower = s[np.tril_indices(s.shape[0])]
    if np.isnan(lower).any():
        raise ValueError("success matrix has NaN on or below the diagonal (a learned skill was not evaluated)")
    if ((lower < 0) | (lower > 1)).any():
        raise ValueError("success rates must lie in [0, 1]")
    s[np.triu_indices(s.shape[0], k=1)] = np.nan
    return s


def afsr_curve(matrix: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """AFSR_k for k = 1..K (Eq. 4)."""
    s = as_success_matrix(matrix)
    return np.array([s[k, : k + 1].mean() for k in range(s.shape[0])])


def prs_curve(
    matrix: Sequence[Sequence[float]] | np.ndarray,
    skills: Sequence[str],
    pairs: Sequence[tuple[str, str]],
) -> np.ndarray:
    """PRS_k for k = 1..K (Eq. 5) over the pre-registered ``pairs``; NaN for k = 1 and while no pair is learned.

    Raises:
        ValueError: a pair names a skill that is not in ``skills``, or ``skills`` has the wrong length.
    """
    s = as_success_matrix(matrix)
    names = [canonical_skill(x) for x in skills]
    if len(names) != s.shape[0]:
        raise ValueError(f"{len(names)} skill names for a {s.shape[0]} x {s.shape[0]} success matrix")
    index = {name: i for i, name in enumerate(names)}
    unknown = sorted({canonical_skill(x) for p in pairs for x in p} - set(index))
    if unknown:
        raise ValueError(f"PRS pairs name skills not in the stream: {unknown}")
    pair_idx = [(index[canonical_skill(a)], index[canonical_skill(b)]) for a, b in pairs]
    out = np.full(s.shape[0], np.nan)
    for k in range(1, s.shape[0]):
        learned = [(i, j) for i, j in pair_idx if i <= k and j <= k]
        if learned:
            out[k] = float(np.mean([min(s[k, i], s[k, j]) for i, j in learned]))
    return out


def bwt_curve(matrix: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """BWT_k = mean_{i<k} (S[k, i] - S[i, i]) for k >= 2 (NaN for k = 1)."""
    s = as_success_matrix(matrix)
    out = np.full(s.shape[0], np.nan)
    for k in range(1, s.shape[0]):
        out[k] = float(np.mean([s[k, i] - s[i, i] for i in range(k)]))
    return out


def principal_subspace(trajectory: np.ndarray, components: int = SPI_COMPONENTS) -> np.ndarray:
    """Top principal directions (d x c, orthonormal columns) of the mean-centred rows of ``trajectory`` (T x d).

    c = min(components, d, T - 1) so that short or low-dimensional trajectories stay defined.
    """
    x = np.asarray(trajectory, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"trajectory must be a T x d array with T >= 2, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("trajectory contains non-finite values")
    x = x - x.mean(axis=0, keepdims=True)
    c = min(components, x.shape[1], x.shape[0] - 1)
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    return vt[:c].T


def subspace_preservation(reference: np.ndarray, current: np.ndarray, components: int = SPI_COMPONENTS) -> float:
    """SPI_i = ||U_ref^T U_cur||_F^2 / c: mean squared cosine of the principal angles between top-c subspaces."""
    u_ref = principal_subspace(reference, components)
    u_cur = principal_subspace(current, components)
    if u_ref.shape[0] != u_cur.shape[0]:
        raise ValueError(f"observation dimensions differ: {u_ref.shape[0]} vs {u_cur.shape[0]}")
    c = min(u_ref.shape[1], u_cur.shape[1])
    if c == 0:
        return float("nan")
    return float(np.linalg.norm(u_ref[:, :c].T @ u_cur[:, :c], "fro") ** 2 / c)


def spi_at_stage(
    reference: Mapping[str, np.ndarray], current: Mapping[str, np.ndarray], earlier_skills: Sequence[str]
) -> float:
    """SPI_k: mean subspace preservation over the earlier skills (i < k); NaN when there are none."""
    if not earlier_skills:
        return float("nan")
    missing = [s for s in earlier_skills if s not in reference or s not in current]
    if missing:
        raise ValueError(f"SPI needs reference and current trajectories for skills {missing}")
    return float(np.mean([subspace_preservation(reference[s], current[s]) for s in earlier_skills]))


def mean_sem(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (ddof = 1) across seeds, ignoring NaN; SEM is NaN for n < 2."""
    v = np.asarray([x for x in values if not (isinstance(x, float) and math.isnan(x))], dtype=np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    if v.size == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(v.size))


def stream_metrics(
    matrix: Sequence[Sequence[float]] | np.ndarray,
    skills: Sequence[str],
    pairs: Sequence[tuple[str, str]],
    spi: Sequence[float] | None = None,
) -> dict[str, list[float] | float]:
    """All per-stage curves and their final values, JSON-ready (NaN kept as float NaN)."""
    curves: dict[str, np.ndarray] = {
        "afsr": afsr_curve(matrix),
        "prs": prs_curve(matrix, skills, pairs),
        "bwt": bwt_curve(matrix),
    }
    if spi is not None:
        curves["spi"] = np.asarray(spi, dtype=np.float64)
    out: dict[str, list[float] | float] = {}
    for name, curve in curves.items():
        out[f"{name}_curve"] = [float(x) for x in curve]
        out[name] = float(curve[-1])
    return out
