"""Continual-learning metrics of the paper (Eqs. 4-5 and Appendix): AFSR, PRS, BWT (two references), SPI.

Conventions. Skills are learned in stream order 1..K. The success matrix ``S`` is K x K with ``S[k, i]`` the
success rate on skill i measured after training through skill k (0-based in code), NaN for i > k (not yet
learned). All ``*_curve`` functions return one value per stage k (NaN where undefined).

* AFSR_k = (1/k) sum_{i<=k} S[k, i]                                            (Eq. 4)
* PRS_k  = (1/|C_k|) sum_{(i,j) in C_k} min(S[k, i], S[k, j]),                 (Eq. 5)
  C_k = the pre-registered pairs whose two skills are both learned by stage k; PRS is defined for k >= 2 and
  is NaN while no pair is complete.
* BWT, two references (GEM sign: negative = forgetting), for k >= 2 (NaN for k = 1):

      bwt_k      = (1/(k-1)) sum_{i<k} (S[k, i] - S[i, i])      reference: after stage i (after its sleep, if any)
      bwt_wake_k = (1/(k-1)) sum_{i<k} (S[k, i] - W_i)          reference: W_i = success on skill i right after
                                                                skill i's own wake, before sleep i

  The paper says only that "BWT is computed from the change in earlier-skill success after learning later
  subtasks" (Appendix A.2, "Evaluation protocol"), without naming the reference. ``bwt`` is GEM's definition on
  the stage matrix (what this project reported before); it
  cannot see what sleep i does to skill i itself: forgetting caused by sleep i on skill i is invisible, and a
  gain of sleep i on skill i raises S[i, i] and is later counted as forgetting. ``bwt_wake`` measures every
  change after the skill's own wake, sleep i included (our choice to report both). For a stage without sleep
  (k = 1, wake-only) W_i = S[i, i]; a wake-only run therefore has bwt_wake == bwt.
* SPI (Synergy Preservation Index), computed on the policy-dependent part of the trajectory only (our choice):
  the robot's own end-effector / tool pose and gripper or jaw (each substrate names its feature indices in one
  constant, ``sr_imitation.substrates.sac.evaluate.SPI_FEATURES`` and
  ``sr_imitation.substrates.act.evaluate.SPI_FEATURES``), as the displacement from the episode's first observation,
  x_t[F] - x_0[F] (:func:`policy_motion`). Object and goal coordinates, and the start pose the environment draws at
  reset, do not depend on the policy; with them in the PCA a policy that does nothing scored 0.5-0.95. For skill i let
  X_ref (T x d) be these motions of the policy right after stage i and X_cur those after stage k, stacked over the
  evaluation episodes (T = all their steps). For each, mean-centre the rows and take the SVD; u_j are the principal
  directions (unit, descending) and lambda_j = sigma_j^2 / (T - 1) the variance along u_j, j <= c = min(3, d,
  T - 1). With tau = ``SPI_VARIANCE_FLOOR`` = 1e-3 (our choice) a direction counts only if its variance is at
  least tau times the reference's top variance:

      R = {a <= c : lambda^ref_a >= tau lambda^ref_1},   C = {b <= c : lambda^cur_b >= tau lambda^ref_1},
      SPI_i^(k) = (1/|R|) sum_{a in R} sum_{b in C} (u^ref_a . u^cur_b)^2                      in [0, 1],
      SPI_k     = mean over the i < k whose SPI_i^(k) is defined, for k >= 2.

  Without the floor a constant trajectory would still have three (arbitrary, noise-determined) principal
  directions; with it a policy that does not move has C empty and scores 0, and one that moves along only one of
  the reference's three directions scores 1/3. Variances (not raw sigma^2) make the comparison independent of
  the number of stacked steps. SPI_i^(k) is undefined (NaN) when the reference itself does not move (lambda^ref_1
  ~ 0: there is no synergy to preserve); such skills are left out of the mean. SPI = 1 means the skill's
  significant top-3 subspace is kept, 0 that it became orthogonal or the policy stopped moving. (The paper
  defines SPI only in words, "preservation of the top-three PCA directions of the reference observation-space
  trajectory"; this is our exact reading, restricted to the policy-dependent features.) With d features, two
  subspaces of c significant directions share at least 2c - d dimensions, so SPI >= (2c - d)/c whenever both
  move in c directions: for Meta-World's d = 4 (hand xyz + gripper) any two moving policies score >= 2/3.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

SPI_COMPONENTS = 3
"""Principal directions compared by SPI (the paper's "top-three PCA directions")."""

SPI_VARIANCE_FLOOR = 1e-3
"""A principal direction counts in SPI only if its variance is >= this fraction of the reference's top variance
(our choice; the paper is silent). Makes SPI of a non-moving policy 0 instead of noise-determined."""


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
    names = list(skills)
    if len(names) != s.shape[0]:
        raise ValueError(f"{len(names)} skill names for a {s.shape[0]} x {s.shape[0]} success matrix")
    index = {name: i for i, name in enumerate(names)}
    unknown = sorted({x for p in pairs for x in p} - set(index))
    if unknown:
        raise ValueError(f"PRS pairs name skills not in the stream: {unknown}")
    pair_idx = [(index[a], index[b]) for a, b in pairs]
    out = np.full(s.shape[0], np.nan)
    for k in range(1, s.shape[0]):
        learned = [(i, j) for i, j in pair_idx if i <= k and j <= k]
        if learned:
            out[k] = float(np.mean([min(s[k, i], s[k, j]) for i, j in learned]))
    return out


def bwt_curve(
    matrix: Sequence[Sequence[float]] | np.ndarray, reference: Sequence[float] | np.ndarray | None = None
) -> np.ndarray:
    """BWT_k = mean_{i<k} (S[k, i] - r_i) for k >= 2 (NaN for k = 1); GEM sign, negative = forgetting.

    Args:
        matrix: the K x K success matrix S (after each stage).
        reference: per-skill reference successes r_i (length K). None: r_i = S[i, i], the success right after
            stage i (``bwt``). The success right after skill i's own wake gives ``bwt_wake`` (module docstring).

    Raises:
        ValueError: ``reference`` has the wrong length, or a value that is missing or outside [0, 1] for a skill
            it is needed for (i < K).
    """
    s = as_success_matrix(matrix)
    n = s.shape[0]
    if reference is None:
        ref = np.diag(s).copy()
    else:
        ref = np.array(reference, dtype=np.float64).reshape(-1)
        if ref.shape != (n,):
            raise ValueError(f"BWT reference has {ref.size} values for a {n} x {n} success matrix")
        used = ref[: n - 1]
        if np.isnan(used).any() or ((used < 0) | (used > 1)).any():
            raise ValueError(f"BWT reference successes must lie in [0, 1] for every skill but the last, got {ref}")
    out = np.full(n, np.nan)
    for k in range(1, n):
        out[k] = float(np.mean([s[k, i] - ref[i] for i in range(k)]))
    return out


def policy_motion(episodes: Sequence[np.ndarray], features: Sequence[int]) -> np.ndarray:
    """The SPI input of one skill: for every episode (T_e x D observations, T_e >= 1) the motion of the
    policy-dependent features from the episode's first observation, x_t[F] - x_0[F], stacked over episodes
    ((sum_e T_e) x |F|). Removing x_0 removes the start pose the environment draws at reset (our choice), so a
    policy that does not move gives an all-zero trajectory.

    Raises:
        ValueError: no episodes, an episode that is not a non-empty 2-D array, or a feature index out of range.
    """
    if len(episodes) == 0:
        raise ValueError("policy_motion needs at least one episode")
    index = [int(f) for f in features]
    if not index:
        raise ValueError("policy_motion needs at least one feature index")
    out = []
    for e, episode in enumerate(episodes):
        x = np.asarray(episode, dtype=np.float64)
        if x.ndim != 2 or x.shape[0] < 1:
            raise ValueError(f"episode {e}: expected a T x D array with T >= 1, got shape {x.shape}")
        bad = [f for f in index if not 0 <= f < x.shape[1]]
        if bad:
            raise ValueError(f"episode {e}: feature indices {bad} out of range for {x.shape[1]}-d observations")
        out.append(x[:, index] - x[0, index])
    return np.concatenate(out)


def principal_components(
    trajectory: np.ndarray, components: int = SPI_COMPONENTS
) -> tuple[np.ndarray, np.ndarray]:
    """Top principal directions (d x c, orthonormal columns) of the mean-centred rows of ``trajectory`` (T x d)
    and the variance along each (sigma_j^2 / (T - 1), descending); c = min(components, d, T - 1).

    Raises:
        ValueError: not a T x d array with T >= 2, or non-finite values.
    """
    x = np.asarray(trajectory, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"trajectory must be a T x d array with T >= 2, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("trajectory contains non-finite values")
    x = x - x.mean(axis=0, keepdims=True)
    c = min(components, x.shape[1], x.shape[0] - 1)
    _, sigma, vt = np.linalg.svd(x, full_matrices=False)
    return vt[:c].T, sigma[:c] ** 2 / (x.shape[0] - 1)


def principal_subspace(trajectory: np.ndarray, components: int = SPI_COMPONENTS) -> np.ndarray:
    """Top principal directions (d x c, orthonormal columns) of the mean-centred rows of ``trajectory`` (T x d),
    c = min(components, d, T - 1) so that short or low-dimensional trajectories stay defined."""
    return principal_components(trajectory, components)[0]


def _is_constant(trajectory: np.ndarray, top_variance: float) -> bool:
    """No motion beyond float rounding: top standard deviation <= 1e-9 of the trajectory's magnitude."""
    scale = 1.0 + float(np.max(np.abs(np.asarray(trajectory, dtype=np.float64))))
    return not top_variance > (1e-9 * scale) ** 2


def subspace_preservation(
    reference: np.ndarray,
    current: np.ndarray,
    components: int = SPI_COMPONENTS,
    variance_floor: float = SPI_VARIANCE_FLOOR,
) -> float:
    """SPI_i = (1/|R|) sum_{a in R, b in C} (u^ref_a . u^cur_b)^2 (module docstring): the mean squared cosine of
    the principal angles between the significant top-c subspaces, where only directions with variance >=
    ``variance_floor`` x the reference's top variance count. A current policy that does not move scores 0; NaN
    when the reference does not move.

    Raises:
        ValueError: the two trajectories have different feature dimensions, or are not valid T x d arrays.
    """
    u_ref, var_ref = principal_components(reference, components)
    u_cur, var_cur = principal_components(current, components)
    if u_ref.shape[0] != u_cur.shape[0]:
        raise ValueError(f"trajectory feature dimensions differ: {u_ref.shape[0]} vs {u_cur.shape[0]}")
    if u_ref.shape[1] == 0 or _is_constant(reference, float(var_ref[0])):
        return float("nan")
    threshold = variance_floor * float(var_ref[0])
    kept_ref = u_ref[:, var_ref >= threshold]
    kept_cur = u_cur[:, var_cur >= threshold]
    if kept_cur.shape[1] == 0:
        return 0.0
    return float(np.linalg.norm(kept_ref.T @ kept_cur, "fro") ** 2 / kept_ref.shape[1])


def spi_at_stage(
    reference: Mapping[str, np.ndarray], current: Mapping[str, np.ndarray], earlier_skills: Sequence[str]
) -> float:
    """SPI_k: mean subspace preservation over the earlier skills (i < k) whose SPI is defined (the reference
    moves); NaN when there are none.

    Raises:
        ValueError: a skill lacks its reference or current trajectories.
    """
    if not earlier_skills:
        return float("nan")
    missing = [s for s in earlier_skills if s not in reference or s not in current]
    if missing:
        raise ValueError(f"SPI needs reference and current trajectories for skills {missing}")
    values = [subspace_preservation(reference[s], current[s]) for s in earlier_skills]
    defined = [v for v in values if not math.isnan(v)]
    return float(np.mean(defined)) if defined else float("nan")


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
    wake_diagonal: Sequence[float] | None = None,
) -> dict[str, list[float] | float]:
    """All per-stage curves and their final values, JSON-ready (NaN kept as float NaN).

    Keys: ``afsr``, ``prs``, ``bwt`` (reference: after stage i), with ``spi`` when given and ``bwt_wake``
    (reference: ``wake_diagonal[i]``, the success on skill i right after its own wake) when ``wake_diagonal`` is
    given; each also as ``<name>_curve`` (one value per stage).
    """
    curves: dict[str, np.ndarray] = {
        "afsr": afsr_curve(matrix),
        "prs": prs_curve(matrix, skills, pairs),
        "bwt": bwt_curve(matrix),
    }
    if wake_diagonal is not None:
        curves["bwt_wake"] = bwt_curve(matrix, wake_diagonal)
    if spi is not None:
        curves["spi"] = np.asarray(spi, dtype=np.float64)
    out: dict[str, list[float] | float] = {}
    for name, curve in curves.items():
        out[f"{name}_curve"] = [float(x) for x in curve]
        out[name] = float(curve[-1])
    return out
