"""One results schema, report and plots for every substrate (``results.json``, ``results.md``, ``metrics.png``,
``success_matrix.png``).

A substrate measures success matrices and trajectories its own way; it hands this module the matrices per
*evaluation unit* (ACT: each evaluation seed, whose episodes reset identically at every stage; SAC: one unit, the
fixed evaluation configurations) and the per-unit SPI curve. Everything else is computed here, once:

- ``bwt`` uses S[i][i] after stage i (after its sleep when there is one), ``bwt_wake`` the success on skill i right
  after its own wake (``sr_imitation.core.metrics``); both per unit, so differences are paired;
- every metric is reported as the mean over units with its standard error, per stage (``curve``) and at the end
  (``final``).

Schema (``results_version`` :data:`RESULTS_VERSION`)::

    results_version, substrate, method, sleep_enabled, label, seed, skills, pairs, eval_units,
    success_matrix            K x K mean over units (null above the diagonal)
    success_matrix_per_unit   U x K x K
    success_after_own_wake    K (the bwt_wake reference; null where not measured)
    success_after_own_wake_per_unit  U x K
    metrics.<afsr|prs|bwt|bwt_wake|spi>: {final, final_sem, final_per_unit, curve, curve_sem}
    spi_features, memory_bytes {skill: bytes}, memory_bytes_total, stages (substrate records), config,
    extra (substrate-specific additions, e.g. ACT's whole success matrix right after each wake),
    code {commit, dirty} (the git commit the writing process started from, :mod:`sr_imitation.infra.provenance`;
    absent in runs written before it was recorded),
    evaluation (where skills were evaluated when not in the substrate's own environment - ACT's --eval.env gym,
    lerobot or none; absent: the needle environment / Meta-World),
    losses (only with evaluation "none": what was measured instead of success, e.g. ACT's memory_loss and
    validation_l1 matrices; success matrices and every metric are then null, eval_units 0)

``label`` names the variant in summaries: the method, or ``wake_only`` for ``sr`` with ``--sleep.enabled=false``.
:func:`upgrade_results` reads the two older per-substrate schemas (ACT 2, SAC 3) into this one for summaries.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sr_imitation.core.memory import memory_contents
from sr_imitation.core.metrics import afsr_curve, bwt_curve, mean_sem, prs_curve
from sr_imitation.infra.provenance import cpu_signature, library_caps, process_code_version
from sr_imitation.io import (
    JSON_CHECKSUM,
    CorruptFileError,
    atomic_write_bytes,
    read_checked_json,
    read_json,
    write_checked_json,
)

RESULTS_VERSION = 5
"""5: the schema of 4, and a file without its ``sha256`` seal is refused (4: one schema for both substrates; before:
ACT 2 with ``final_mean`` dictionaries, SAC 3 with bare floats)."""
SEALED_SINCE = 5
"""The first ``results_version`` whose files must carry their seal. Older files (committed raw outputs of earlier
versions, some written before JSON checksums) are read without one and reported as unsealed; whether a file may lack
its seal is decided by its recorded version, never by the missing key alone."""

METRICS = ("afsr", "prs", "bwt", "bwt_wake", "spi")
LABELS = {"afsr": "AFSR", "prs": "PRS", "bwt": "BWT (ref. after stage i)",
          "bwt_wake": "BWT_wake (ref. after own wake)", "spi": "SPI"}
LOSS_METRICS = {"val_l1": "validation_l1", "memory_loss": "memory_loss"}
"""The final metrics of runs without closed-loop evaluation (``losses``, ``--eval.env=none``: e.g. a real robot's
datasets and no simulator): the mean over skills, under the final policy, of each skill's validation l1 (the
behaviour-cloning l1 on its held-out demonstration episodes, the same episodes for every variant of a training seed)
or of its stored memory's distillation loss (skills whose method stores no memory left out). Lower is better."""


def final_loss(results: Mapping[str, Any], metric: str) -> float | None:
    """A run's final :data:`LOSS_METRICS` value (the last row of ``losses[...]``, mean over the skills measured);
    ``None`` for a run that did not record it (an evaluated run)."""
    rows = (results.get("losses") or {}).get(LOSS_METRICS[metric]) or []
    last = [float(x) for x in (rows[-1] if rows else []) if x is not None and math.isfinite(x)]
    return float(np.mean(last)) if last else None


def final_headline(results: Mapping[str, Any]) -> str:
    """A run's final number in words for log and status lines: ``AFSR 0.933``, or for a run without evaluation
    ``validation l1 0.5990 (no evaluation)`` (:func:`final_loss`), else ``AFSR -``."""
    afsr = ((results.get("metrics") or {}).get("afsr") or {}).get("final")
    if afsr is not None:
        return f"AFSR {afsr:.3f}"
    l1 = final_loss(results, "val_l1")
    return "AFSR -" if l1 is None else f"validation l1 {l1:.4f} (no evaluation)"


def variant_label(method: str, sleep_enabled: bool) -> str:
    """The name a run's variant has in tables: ``sr`` without sleep is the paper's "SR Wake-Only"."""
    return "wake_only" if method == "sr" and not sleep_enabled else method


def unit_mean(s: np.ndarray) -> np.ndarray:
    """Mean over evaluation units (axis 0), NaN where no unit has a value (no warning for all-NaN cells)."""
    with np.errstate(invalid="ignore"):
        counts = np.sum(~np.isnan(s), axis=0)
        total = np.nansum(s, axis=0)
        return np.where(counts > 0, total / np.maximum(counts, 1), np.nan)


def metric_curves(s: np.ndarray, skills: Sequence[str], pairs: Sequence[tuple[str, str]],
                  wake_diagonal: np.ndarray | None) -> dict[str, np.ndarray]:
    """AFSR, PRS, BWT and (with ``wake_diagonal``, U x K) BWT_wake curves per unit from S (U x K x K)."""
    curves = {
        "afsr": np.stack([afsr_curve(m) for m in s]),
        "prs": np.stack([prs_curve(m, skills, pairs) if pairs else np.full(len(skills), np.nan) for m in s]),
        "bwt": np.stack([bwt_curve(m) for m in s]),
    }
    if wake_diagonal is not None:
        curves["bwt_wake"] = np.stack([bwt_curve(m, w) for m, w in zip(s, wake_diagonal, strict=True)])
    return curves


def summarize_curve(curves: np.ndarray) -> dict[str, Any]:
    """Per-stage mean and SE over units (U x K), and the final value."""
    stats = [mean_sem([float(x) for x in curves[:, k]]) for k in range(curves.shape[1])]
    return {"final": stats[-1][0], "final_sem": stats[-1][1], "final_per_unit": curves[:, -1].tolist(),
            "curve": [m for m, _ in stats], "curve_sem": [e for _, e in stats]}


def memory_budget(memories: Sequence[Any]) -> tuple[dict[str, int], dict[str, int]]:
    """Bytes of the stored tensors of ``memories`` (a continual method's memory budget) per skill and per memory
    kind (``sac_critic``, ``ewc_fisher``, ``output_distillation``, ``transitions``, ...)."""
    per_skill: dict[str, int] = {}
    per_kind: dict[str, int] = {}
    for m in memories:
        per_skill[m.skill] = per_skill.get(m.skill, 0) + int(m.nbytes())
        per_kind[m.kind] = per_kind.get(m.kind, 0) + int(m.nbytes())
    return per_skill, per_kind


def _unmeasured(k: int) -> dict[str, Any]:
    """A metric that was not measured (no evaluation): null, not 0."""
    return {"final": None, "final_sem": None, "final_per_unit": [], "curve": [None] * k, "curve_sem": [None] * k}


def build_results(*, substrate: str, method: str, sleep_enabled: bool, seed: int, skills: Sequence[str],
                  pairs: Sequence[tuple[str, str]], success: np.ndarray | None, after_wake: np.ndarray | None,
                  spi: np.ndarray | None, spi_features: Sequence[int], memory_bytes: Mapping[str, int],
                  stages: list[Any], config: Mapping[str, Any], extra: Mapping[str, Any] | None = None,
                  memory_kinds: Mapping[str, int] | None = None, evaluation: str | None = None,
                  losses: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The results dictionary (JSON-ready, NaN as null).

    ``success``: S per unit (U x K x K, NaN above the diagonal); ``after_wake``: each skill's success right after
    its own wake per unit (U x K, NaN where not measured: then ``bwt_wake`` is null); ``spi``: SPI per unit and
    stage (U x K, NaN at k = 1). ``success=None`` (no evaluation, ``evaluation="none"``): every metric and success
    entry is null and ``losses`` says what was measured instead. ``evaluation``: see the module docstring."""
    k_total = len(skills)
    if success is None:
        metrics = {name: _unmeasured(k_total) for name in METRICS}
        nothing = [[None] * k_total for _ in range(k_total)]
        matrices = {"eval_units": 0, "success_matrix": nothing, "success_matrix_per_unit": [],
                    "success_after_own_wake": [None] * k_total, "success_after_own_wake_per_unit": []}
    else:
        if after_wake is None or spi is None:
            raise ValueError("build_results: a measured success needs after_wake and spi (NaN where not measured)")
        measured = not np.isnan(after_wake[:, :-1]).any()
        curves = metric_curves(success, skills, pairs, after_wake if measured else None)
        curves["spi"] = np.asarray(spi, dtype=np.float64)
        metrics = {name: summarize_curve(curves[name]) for name in METRICS if name in curves}
        if "bwt_wake" not in metrics:  # --eval.after_wake=false: the reference was not measured
            metrics["bwt_wake"] = summarize_curve(np.full_like(curves["bwt"], np.nan))
        matrices = {"eval_units": int(success.shape[0]), "success_matrix": unit_mean(success).tolist(),
                    "success_matrix_per_unit": success.tolist(),
                    "success_after_own_wake": unit_mean(after_wake).tolist(),
                    "success_after_own_wake_per_unit": after_wake.tolist()}
    results = {
        "results_version": RESULTS_VERSION,
        "substrate": substrate,
        "method": method,
        "sleep_enabled": bool(sleep_enabled),
        "label": variant_label(method, sleep_enabled),
        "seed": seed,
        "skills": list(skills),
        "pairs": [list(p) for p in pairs],
        **matrices,
        "metrics": metrics,
        "spi_features": [int(f) for f in spi_features],
        "memory_bytes": {k: int(v) for k, v in memory_bytes.items()},
        "memory_bytes_total": int(sum(memory_bytes.values())),
        "memory_kinds": {k: int(v) for k, v in (memory_kinds or {}).items()},
        # what each kind holds, in words, from the memory classes that wrote them (summaries read it from here)
        "memory_contents": {k: memory_contents(k) for k in (memory_kinds or {})},
        "stages": stages,
        "config": dict(config),
        "extra": dict(extra or {}),
        "code": dict(process_code_version()),
        # of the run's last phase; library_caps: the kernel choices forced by the environment (provenance.py)
        "machine": {"cpu": cpu_signature()["name"], "avx512": cpu_signature()["avx512"],
                    "library_caps": library_caps()},
    }
    if evaluation is not None:
        results["evaluation"] = evaluation
    if losses is not None:
        results["losses"] = dict(losses)
    # numpy scalars as floats; NaN (an undefined metric, e.g. PRS at k = 1) and infinities as null
    return json.loads(json.dumps(results, default=float), parse_constant=lambda _: None)


def _fmt(mean: float | None, sem: float | None = None) -> str:
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "n/a"
    if sem is None or (isinstance(sem, float) and math.isnan(sem)):
        return f"{mean:.3f}"
    return f"{mean:.3f} +- {sem:.3f}"


def _cell(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def episodes_per_cell(results: Mapping[str, Any]) -> int | None:
    """The episodes one success cell of a run pools (episodes per evaluation unit x units); None when not recorded."""
    episodes = ((results.get("config") or {}).get("eval") or {}).get("episodes")
    if not isinstance(episodes, int) or episodes < 1 or not results.get("eval_units"):
        return None
    return episodes * int(results["eval_units"])


def binomial_se_bound(n: int) -> float:
    """The largest binomial SE of a success rate over ``n`` episodes: sqrt(p (1 - p) / n) at p = 0.5."""
    return math.sqrt(0.25 / n)


def _binomial_note(results: Mapping[str, Any]) -> list[str]:
    """The evaluation noise of one success cell: a rate over N episodes has binomial SE sqrt(p (1 - p) / N), at most
    sqrt(0.25 / N); the SE over a few evaluation units printed beside the metrics understates it."""
    n = episodes_per_cell(results)
    if n is None:
        return []
    episodes = n // int(results["eval_units"])
    return [f"A success cell pools {n} episodes ({episodes} per evaluation unit): its binomial SE is up to "
            f"{binomial_se_bound(n):.3f} (at 0.5 success); the SE over evaluation units understates that noise."]


def render_markdown(results: Mapping[str, Any]) -> str:
    """``results.md``: final metrics (mean +- SE over evaluation units), success matrix, success after own wake."""
    skills = results["skills"]
    units = results["eval_units"]
    lines = [f"# Stream results ({results['substrate']}, {results['label']}, seed {results['seed']})", ""]
    if results.get("evaluation") == "none":
        return "\n".join(lines + _losses_markdown(results))
    if results.get("evaluation"):
        lines += [f"Evaluation: {results['evaluation']} (--eval.env).", ""]
    lines += [f"Mean +- SE over {units} evaluation unit(s) (ACT: evaluation seeds; SAC: one set of fixed evaluation "
              "configurations).", *_binomial_note(results), "",
              "| metric | final (k = K) | per stage |", "|---|---|---|"]
    for name in METRICS:
        m = results["metrics"][name]
        curve = ", ".join("-" if x is None else f"{x:.3f}" for x in m["curve"])
        lines.append(f"| {LABELS[name]} | {_fmt(m['final'], m['final_sem'])} | {curve} |")
    lines += _prs_note(results)
    lines += ["", "Success S[k][i] (rows: after stage k; mean over evaluation units):", "",
              "| after \\ skill | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
    for k, row in enumerate(results["success_matrix"]):
        lines.append(f"| {skills[k]} | " + " | ".join(_cell(x) if i <= k else "" for i, x in enumerate(row)) + " |")
    lines.append("| right after own wake | " + " | ".join(_cell(x) for x in results["success_after_own_wake"]) + " |")
    lines += ["", f"Continual-learning memory stored: {results['memory_bytes_total'] / 1e6:.2f} MB", ""]
    code = results.get("code") or {}
    if code.get("commit"):
        lines += [f"Code: commit {code['commit']}" + (" with uncommitted changes" if code.get("dirty") else ""), ""]
    return "\n".join(lines)


def _prs_note(results: Mapping[str, Any]) -> list[str]:
    """Why PRS is n/a, where it is: one skill, or a pair list holding no pair of the stream's skills."""
    if results["metrics"]["prs"]["final"] is not None:
        return []
    if len(results["skills"]) < 2:
        return ["", "PRS is n/a: it needs two skills (Eq. 5)."]
    if not results.get("pairs"):
        chosen = ((results.get("config") or {}).get("stream") or {}).get("pairs")
        flag = f" (--stream.pairs={chosen})" if chosen else ""
        return ["", f"PRS is n/a: the pair list{flag} holds no pair of this stream's skills; --stream.pairs=mt5 "
                    "(Meta-World's MT5 skills), all or adjacent give it pairs."]
    return []


def _losses_markdown(results: Mapping[str, Any]) -> list[str]:
    """``results.md`` of a run without evaluation: what was measured instead of success (``losses``)."""
    skills, losses = results["skills"], results.get("losses") or {}
    lines = ["Evaluation: none (--eval.env=none): no closed-loop success was measured, so AFSR, PRS, BWT and SPI are "
             "n/a. Measured instead, under the policy after each stage (rows) for each learned skill (columns):", ""]
    tables = [("memory_loss", "Memory loss L_i (the distillation loss of skill i's stored memory; - where the method "
                              "stores no actor memory)"),
              ("validation_l1", "Validation l1 (the wake's behaviour-cloning l1 on skill i's validation episodes)")]
    for key, title in tables:
        if key not in losses:
            continue
        lines += [f"{title}:", "", "| after \\ skill | " + " | ".join(skills) + " |", "|---" * (len(skills) + 1) + "|"]
        for k, row in enumerate(losses[key]):
            lines.append(f"| {skills[k]} | " + " | ".join(_cell(x, 4) if i <= k else "" for i, x in enumerate(row))
                         + " |")
        after_wake = losses.get(f"{key}_after_wake")
        if after_wake is not None:
            diagonal = [_cell(after_wake[i][i], 4) for i in range(len(skills))]
            lines.append("| right after own wake | " + " | ".join(diagonal) + " |")
        lines.append("")
    if losses.get("wake_best_val_l1"):
        lines += ["Best validation l1 of each wake: " + ", ".join(
            f"{s} {_cell(v, 4)}" for s, v in zip(skills, losses["wake_best_val_l1"], strict=True)), ""]
    lines += [f"Continual-learning memory stored: {results['memory_bytes_total'] / 1e6:.2f} MB", ""]
    code = results.get("code") or {}
    if code.get("commit"):
        lines += [f"Code: commit {code['commit']}" + (" with uncommitted changes" if code.get("dirty") else ""), ""]
    return lines


def save_figure(fig: Any, path: Path) -> None:
    """Write a matplotlib figure as a PNG atomically (tight layout, 110 dpi) and close it.

    Args:
        fig: the figure.
        path: the PNG file.
    """
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def write_plots(results: Mapping[str, Any], out: Path) -> None:
    """``metrics.png`` (AFSR, PRS, BWT and BWT_wake, SPI against k, shaded +- SE, like the paper's Figure 2) and
    ``success_matrix.png`` (heatmap of S[k][i] with the after-own-wake row)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    skills = results["skills"]
    ks = np.arange(1, len(skills) + 1)
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.2))
    for ax, names in zip(axes, (("afsr",), ("prs",), ("bwt", "bwt_wake"), ("spi",)), strict=True):
        for name in names:
            m = results["metrics"][name]
            mean = np.array([np.nan if x is None else x for x in m["curve"]], dtype=float)
            sem = np.array([0.0 if x is None else x for x in m["curve_sem"]], dtype=float)
            ax.plot(ks, mean, marker="o", label=LABELS[name])
            ax.fill_between(ks, mean - sem, mean + sem, alpha=0.25)
        ax.set_title(" / ".join(name.upper() for name in names))
        if len(names) > 1:
            ax.legend(fontsize=7)
        ax.set_ylim(*((-1.05, 1.05) if names[0] == "bwt" else (-0.02, 1.05)))
        ax.set_xlabel("skills learned k")
        ax.set_xticks(ks)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{results['substrate']} / {results['label']} / seed {results['seed']}", fontsize=9)
    save_figure(fig, out / "metrics.png")

    s = np.array([[np.nan if x is None else x for x in row] for row in results["success_matrix"]], dtype=float)
    wake = np.array([np.nan if x is None else x for x in results["success_after_own_wake"]], dtype=float)
    grid = np.vstack([s, wake[None, :]])
    fig, ax = plt.subplots(figsize=(1.2 * len(skills) + 2.5, 1.0 * len(skills) + 2.0))
    im = ax.imshow(np.ma.masked_invalid(grid), vmin=0, vmax=1, cmap="viridis")
    for (k, i), v in np.ndenumerate(grid):
        if not np.isnan(v):
            ax.text(i, k, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.6 else "k", fontsize=8)
    ax.axhline(len(skills) - 0.5, color="w", lw=2)
    ax.set_xticks(range(len(skills)), skills, rotation=30, ha="right")
    ax.set_yticks(range(len(skills) + 1), [f"after {x}" for x in skills] + ["right after own wake"])
    ax.set_xlabel("evaluated skill i")
    ax.set_title("success S[k][i]")
    fig.colorbar(im, ax=ax, fraction=0.046)
    save_figure(fig, out / "success_matrix.png")


def write_results(out: Path, results: Mapping[str, Any], plots: bool = True) -> None:
    """``results.json`` and ``results.md`` (atomic), and the plots unless ``plots`` is false."""
    write_checked_json(out / "results.json", results)
    atomic_write_bytes(out / "results.md", render_markdown(results).encode())
    if plots:
        write_plots(results, out)


def upgrade_results(results: Mapping[str, Any]) -> dict[str, Any]:
    """A results dictionary of any version as schema :data:`RESULTS_VERSION` (the fields summaries read).

    ACT runs of schemas 1-2 (``metrics[m]["final_mean"]``, per evaluation seed) and SAC runs of schemas 1-3 (bare
    floats, one unit) are converted; metrics a run did not measure are null, except that a SAC wake-only run
    without ``bwt_wake`` has it equal to ``bwt`` (its after-wake and after-stage policies are the same), and an ACT run
    without it has it computed from its after-wake matrix. Raises ``ValueError`` for unknown versions."""
    version = results.get("results_version")
    if version in (4, RESULTS_VERSION):  # 5 = 4 + mandatory seal
        return {**results, "results_version": RESULTS_VERSION}
    if version in (None, 1, 2) and "success_matrix_per_seed" in results:  # ACT
        def metric(m: Mapping[str, Any] | None) -> dict[str, Any]:
            if m is None:
                return {"final": None, "final_sem": None, "final_per_unit": [], "curve": [], "curve_sem": []}
            return {"final": m["final_mean"], "final_sem": m["final_sem"], "final_per_unit": m["final_per_seed"],
                    "curve": m["mean_curve"], "curve_sem": m["sem_curve"]}

        if "memory_bytes_total" not in results:
            results = {**results, "memory_bytes_total": sum((results.get("memory_bytes") or {}).values())}

        sleep = results.get("policy_sleep", True)
        method = results.get("method", "sr")
        metrics = {name: metric(results["metrics"].get(name)) for name in METRICS}
        wake = results.get("success_after_own_wake")
        if wake is None and "success_matrix_after_wake" in results:  # schema 1: only the whole after-wake matrix
            wake = np.diag(np.array(results["success_matrix_after_wake"], dtype=float)).tolist()
        if metrics["bwt_wake"]["final"] is None and wake is not None:  # linear in S: the mean of the per-unit values
            s = np.array([[np.nan if x is None else x for x in row] for row in results["success_matrix"]], float)
            metrics["bwt_wake"]["final"] = float(bwt_curve(s, np.array(wake, dtype=float))[-1])
        return {**results, "results_version": RESULTS_VERSION, "substrate": "act", "sleep_enabled": bool(sleep),
                "label": variant_label(method, bool(sleep)), "eval_units": len(results["success_matrix_per_seed"]),
                "success_after_own_wake": wake or [None] * len(results["skills"]), "metrics": metrics}
    if version in (None, 2, 3) and "success_matrix" in results:  # SAC (unversioned, 2, 3)
        m = results["metrics"]
        label = results["method"]
        method = results.get("method_name", "sr" if label in ("sleeping_robots", "wake_only") else label)

        def metric(name: str) -> dict[str, Any]:
            value, curve = m.get(name), m.get(f"{name}_curve", [])
            if name == "bwt_wake" and value is None and label == "wake_only":
                value, curve = m.get("bwt"), m.get("bwt_curve", [])
            return {"final": value, "final_sem": None, "final_per_unit": [value], "curve": curve,
                    "curve_sem": [None] * len(curve)}

        wake = results.get("success_after_own_wake") or [None] * len(results["skills"])
        return {**results, "results_version": RESULTS_VERSION, "substrate": "sac", "method": method,
                "sleep_enabled": label != "wake_only", "label": "sr" if label == "sleeping_robots" else label,
                "eval_units": 1, "success_after_own_wake": wake, "metrics": {name: metric(name) for name in METRICS},
                "memory_bytes_total": results.get("memory_nbytes_total", 0)}
    raise ValueError(f"results_version {version!r} is not a version this code reads (it reads 1-{RESULTS_VERSION})")


def read_results_file(path: Path) -> tuple[dict[str, Any], bool]:
    """A ``results.json`` as written (not upgraded) and whether it is unsealed. A sealed file must match its seal; a
    file without one is read only if its ``results_version`` predates :data:`SEALED_SINCE` and its numbers are what
    that schema wrote (:func:`unsealed_problem`: the AFSR it records is the one its success matrix gives);
    :class:`~sr_imitation.io.CorruptFileError` naming the file otherwise."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict):
        raise CorruptFileError(path, "not a JSON object")
    if JSON_CHECKSUM in data or _version_number(data) >= SEALED_SINCE:
        return read_checked_json(path), False
    problem = unsealed_problem(data)
    if problem is not None:
        raise CorruptFileError(path, f"unsealed (results_version {data.get('results_version')}) and {problem}: "
                                     "edited or damaged, not read")
    return data, True


def unsealed_problem(data: Mapping[str, Any]) -> str | None:
    """Why an unsealed results dictionary is not what its schema wrote (``None`` if it is): every recorded AFSR
    (per stage and final) must be the mean of the success matrix's row up to the diagonal (Eq. 4), and every recorded
    BWT and BWT_wake (per stage where the schema kept the curve, and final) what the success matrix and the success
    after each own wake give (Eq. 6, linear in the matrix, so the mean over evaluation units is the matrix's), to
    1e-6. PRS and SPI are not recomputable from the mean matrix (PRS is taken per evaluation unit; SPI from
    trajectories), so they go unchecked in an unsealed file."""
    try:
        results = upgrade_results(data)
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        return f"does not read as its schema ({type(exc).__name__}: {exc})"
    shape = schema_problem(results)
    if shape is not None:
        return f"does not read as its schema ({shape})"
    matrix = results.get("success_matrix")
    afsr = (results.get("metrics") or {}).get("afsr") or {}
    if not isinstance(matrix, list) or afsr.get("final") is None:
        return None  # nothing measured (no evaluation): no AFSR to check
    try:
        full = np.array([[np.nan if x is None else float(x) for x in row] for row in matrix], dtype=float)
        rows = [row[: k + 1] for k, row in enumerate(full)]
        expected = [float(np.nanmean(row)) if not all(np.isnan(row)) else None for row in rows]
    except (TypeError, ValueError):
        return "holds a success matrix that is not numbers"
    recorded = list(afsr.get("curve") or [])
    if len(recorded) == len(expected):
        for k, (a, b) in enumerate(zip(recorded, expected, strict=True)):
            if a is not None and b is not None and abs(float(a) - b) > 1e-6:
                return f"its AFSR after stage {k + 1} ({a}) is not its success matrix's ({b:.6f})"
    if expected and expected[-1] is not None and abs(float(afsr["final"]) - expected[-1]) > 1e-6:
        return f"its final AFSR ({afsr['final']}) is not its success matrix's ({expected[-1]:.6f})"
    return _bwt_problem(results, full)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers_problem(values: Any, where: str) -> str | None:
    """Why ``values`` is not a list of numbers or nulls (``None`` if it is)."""
    if not isinstance(values, list):
        return f"{where} is {type(values).__name__}, not a list"
    for i, value in enumerate(values):
        if value is not None and not _is_number(value):
            return f"{where}[{i}] is {type(value).__name__}, not a number"
    return None


def schema_problem(results: Mapping[str, Any]) -> str | None:
    """Why an upgraded results dictionary (:func:`upgrade_results`) does not hold what the reports read where they
    read it (``None`` if it does): the skills, the success matrix and after-wake success as numbers or nulls, each
    metric's final value and curve as numbers or nulls. A file of another schema relabelled with an older
    ``results_version`` (``metrics.afsr.final`` a dictionary under version 3) is named so, never a traceback."""
    if not isinstance(results.get("skills"), list):
        return "skills is not a list"
    matrix = results.get("success_matrix")
    if not isinstance(matrix, list):
        return f"success_matrix is {type(matrix).__name__}, not a list of rows"
    for k, row in enumerate(matrix):
        problem = _numbers_problem(row, f"success_matrix[{k}]")
        if problem is not None:
            return problem
    problem = _numbers_problem(results.get("success_after_own_wake"), "success_after_own_wake")
    if problem is not None:
        return problem
    metrics = results.get("metrics")
    if not isinstance(metrics, Mapping):
        return f"metrics is {type(metrics).__name__}, not an object"
    for name in METRICS:
        metric = metrics.get(name)
        if metric is None:
            continue
        if not isinstance(metric, Mapping):
            return f"metrics.{name} is {type(metric).__name__}, not an object"
        final = metric.get("final")
        if final is not None and not _is_number(final):
            return f"metrics.{name}.final is {type(final).__name__}, not a number"
        problem = _numbers_problem(metric.get("curve", []), f"metrics.{name}.curve")
        if problem is not None:
            return problem
    return None


def _bwt_problem(results: Mapping[str, Any], matrix: np.ndarray) -> str | None:
    """Where an unsealed file's recorded BWT / BWT_wake differ from its success matrix's (see
    :func:`unsealed_problem`); references with a missing entry are not checked."""
    after_wake = results.get("success_after_own_wake")
    for name, reference in (("bwt", None), ("bwt_wake", after_wake)):
        recorded = (results.get("metrics") or {}).get(name) or {}
        if recorded.get("final") is None or (name == "bwt_wake" and (
                not isinstance(reference, list) or any(x is None for x in reference[:-1]))):
            continue
        try:
            ref = None if reference is None else [np.nan if x is None else float(x) for x in reference]
            expected = bwt_curve(matrix, ref)
        except (TypeError, ValueError):
            return f"its {name} cannot be recomputed from its success matrix"
        curve = list(recorded.get("curve") or [])
        pairs = list(zip(curve, expected, strict=True)) if len(curve) == len(expected) else []
        for k, (a, b) in enumerate(pairs):
            if a is not None and not np.isnan(b) and abs(float(a) - b) > 1e-6:
                return f"its {name} after stage {k + 1} ({a}) is not its success matrix's ({b:.6f})"
        if abs(float(recorded["final"]) - expected[-1]) > 1e-6:
            return f"its final {name} ({recorded['final']}) is not its success matrix's ({expected[-1]:.6f})"
    return None


def load_results(run: Path) -> dict[str, Any]:
    """``<run>/results.json`` in the current schema, its seal checked; a missing file is named. A file without a
    seal is read only as :func:`read_results_file` allows; it is then marked ``"unsealed": true`` (reports mark such
    runs in their rows)."""
    path = Path(run) / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results (unfinished run?)")
    data, unsealed = read_results_file(path)
    try:
        results = upgrade_results(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return {**results, "unsealed": unsealed}


def _version_number(data: Mapping[str, Any]) -> int:
    version = data.get("results_version")
    return version if isinstance(version, int) and not isinstance(version, bool) else 0  # absent: the first schema
