"""Sleep consolidation (Algorithm 1, lines 7-15; Section 3, Eqs. 1-2).

One sleep phase after skill k >= 2, over the memories S_k = {M_1..M_k}:

1. set the anchor coefficient lambda_k by Eq. 2 (:func:`anchor_coefficient`);
2. repeat up to ``max_iterations`` times: per-memory gradients g_i of L_i(theta) on a fresh batch from each
   memory's buffer, Nash (or mean / PCGrad) aggregation on their Gram matrix, the anchored direction
   d = g* + lambda_k (theta - theta_{k-1}^sleep), an Adam step with eta_sleep, the optional step callback
   (homeostatic excitability), and early stopping when the windowed sleep objective plateaus.

The loop is substrate-agnostic: it needs the policy's trainable parameters, a callable that the memories
evaluate, and the memories. A non-finite loss or gradient never updates the policy: the step is skipped and
recorded, and ``max_nonfinite_steps`` consecutive skips raise :class:`NonFiniteSleepError`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sr_imitation.core.aggregation import Aggregator, make_aggregator
from sr_imitation.core.memory import Memory, per_memory_losses
from sr_imitation.progress import Progress

logger = logging.getLogger(__name__)


EARLY_STOP_SCALES = ("window", "memory_scale")
"""The values of :attr:`SleepConfig.early_stop_scale`."""


class NonFiniteSleepError(FloatingPointError):
    """Sleep met too many consecutive non-finite losses or gradients; the policy was not updated by them."""


@dataclass
class SleepConfig:
    """Sleep hyperparameters. Defaults follow the paper's MT5 table ("Sleep-consolidation hyperparameters"); the
    SurgicAI table's values are the ACT substrate's preset
    (:class:`sr_imitation.substrates.act.config.SurgicAISleepConfig`) and whether a run sleeps at all is the stream's
    setting (:class:`sr_imitation.stream.config.StreamSleepConfig`).

    Each field is documented below (``sr-train --help`` shows it).
    """

    lr: float = 5e-4
    """Adam learning rate eta_sleep (MT5 5e-4, SurgicAI 1e-5)."""
    max_iterations: int = 4000
    """N_sleep, iterations per sleep at most (MT5 4000, SurgicAI 1000)."""
    batch_size: int = 64
    """Samples drawn from each memory per iteration (MT5 64, SurgicAI 8)."""
    aggregator: str = "nash"
    """nash (Eq. 1 solved exactly), nash_fw (the paper's Frank-Wolfe with fw_iterations - approximate, the
    ablation), mean_grad (raw-gradient mean - the paper's Mean-grad ablation), mean_normalized or pcgrad."""
    fw_iterations: int = 50
    """Frank-Wolfe iterations per solve of nash_fw (paper - MT5 50, SurgicAI 5); nash stops at its tolerance."""
    eps: float = 1e-5
    """Gradient-normalization constant of g / (||g|| + eps)."""
    early_stop_tol: float = 1e-3
    """delta - stop when the windowed sleep objective changes by less than this."""
    early_stop_window: int = 100
    """Window length in iterations of the plateau rule (MT5 100, SurgicAI 50)."""
    early_stop_relative: bool = True
    """Compare the change of window means relative to the previous window mean (true) or absolutely (false); the
    paper does not say (our choice - keeps the rule meaningful for the small imitation losses)."""
    early_stop_scale: str = "window"
    """What the plateau rule's change is measured against: ``window`` - the previous window's mean (or nothing, with
    ``early_stop_relative=false``), as the paper's rule reads; ``memory_scale`` - the mean over the sleep's memories
    of each memory's own scale at the sleep's start (:meth:`Memory.scale`: a frozen critic's action gap), for
    objectives whose level says nothing of how much they can still change (a critic's value of -892 moving by 0.5
    is 0.06 % of its level; our choice)."""
    anchor_strength: float = 1e-2
    """lambda of the proximal anchor (Eq. 2); 0 is the no-anchor ablation."""
    anchor_tau: float | None = 150.0
    """tau of the anchor gate (Eq. 2; MT5 150); null - always on (SurgicAI)."""
    anchor_after_final: bool = False
    """Apply the anchor in the sleep after the final skill (MT5 no, SurgicAI yes)."""
    newest_guard: bool = False
    """Stop the sleep at the end of the first early-stop window whose mean loss of the newest memory (the last one)
    is at or above the mean, over the older memories, of their own window-mean losses, keeping the parameters at that
    point: a sleep that stops before it spends the newest skill on the older ones (our choice, candidate C3 of the
    final-sleep screening protocol in docs/RESULTS.md; off - the paper's sleep)."""
    max_nonfinite_steps: int = 10
    """Consecutive skipped (non-finite) steps before the sleep raises."""
    seed: int = 0
    """Seeds the memory batch sampler (and PCGrad's order); stream substrates set it per stage from --seed."""
    joint_forward: bool = False
    """Evaluate same-kind memories in one forward pass and take the k per-memory gradients from one backward pass
    batched over the k losses (``is_grads_batched``): fewer kernel launches (2.9x at k = 5, 1.8x at k = 3) for k times
    the backward arithmetic. On an H200 a whole sleep iteration is 1.8-3.2x faster with it (state-only k = 3, batch
    32: 15.7 vs 37.6 ms; with the camera 41.9 vs 77.6 ms); on the CPU 2-3x slower. Before 2026-11-27 the stream's
    memories, each naming its own checkpoint, were never grouped, so this ran k forwards plus the batched backward
    and was slower on the GPU too (``Memory.provenance_keys``). The same values up to float summation order (our
    choice; off by default: the CPU is this project's machine; docs/BENCHMARKS.md)."""

    def __post_init__(self) -> None:
        checks = {  # rule text, holds
            "lr": ("> 0", self.lr > 0),
            "max_iterations": (">= 1", self.max_iterations >= 1),
            "batch_size": (">= 1", self.batch_size >= 1),
            "fw_iterations": (">= 1", self.fw_iterations >= 1),
            "eps": ("> 0", self.eps > 0),
            "early_stop_tol": (">= 0", self.early_stop_tol >= 0),
            "early_stop_window": (">= 1", self.early_stop_window >= 1),
            "anchor_strength": (">= 0", self.anchor_strength >= 0),
            "anchor_tau": ("> 0 or null", self.anchor_tau is None or self.anchor_tau > 0),
            "max_nonfinite_steps": (">= 1", self.max_nonfinite_steps >= 1),
            "early_stop_scale": (f"one of {list(EARLY_STOP_SCALES)}", self.early_stop_scale in EARLY_STOP_SCALES),
        }
        # the key as the command line names it (--sleep.<key>): every stream config holds it under ``sleep``
        bad = [f"sleep.{k} must be {rule}, got {getattr(self, k)!r}" for k, (rule, ok) in checks.items() if not ok]
        if bad:
            raise ValueError("; ".join(bad))
        from sr_imitation.core.aggregation import AGGREGATORS

        if self.aggregator not in AGGREGATORS:
            from sr_imitation.core.aggregation import make_aggregator as _check

            _check(self.aggregator)  # raises with the list of names

    @classmethod
    def mt5(cls, **overrides: Any) -> SleepConfig:
        """Paper Table "Sleep-consolidation hyperparameters for MT5" (tau = 150, no anchor after the final skill)."""
        return cls(**overrides)

    def make_aggregator(self) -> Aggregator:
        kwargs: dict[str, Any] = {"eps": self.eps}
        if self.aggregator == "nash_fw":
            kwargs["iterations"] = self.fw_iterations
        elif self.aggregator == "pcgrad":
            kwargs["seed"] = self.seed
        return make_aggregator(self.aggregator, **kwargs)


@dataclass
class SleepResult:
    """Diagnostics of one sleep phase (per-iteration arrays have one row per attempted iteration)."""

    skills: list[str]
    anchor_lambda: float
    anchor_distances: list[float]
    stop_iteration: int
    stop_reason: str
    alpha: list[list[float]] = field(default_factory=list)
    grad_norms: list[list[float]] = field(default_factory=list)
    memory_losses: list[list[float]] = field(default_factory=list)
    sleep_objective: list[float] = field(default_factory=list)
    solver_iterations: list[int] = field(default_factory=list)
    solver_status: dict[str, int] = field(default_factory=dict)
    skipped_steps: list[dict[str, Any]] = field(default_factory=list)
    early_stop_scale: float | None = None
    """The memories' scale the plateau rule was measured against (``early_stop_scale=memory_scale``); else none."""
    cosines_first_last: list[list[list[float]]] = field(default_factory=list)
    """The cosine matrix C of the memory gradients (the matrix Eq. 1 bargains over, ``aggregation/_nash.py``) at the
    sleep's first and last iteration; a zero gradient's row and column are 0. Our addition for reading the weights:
    Eq. 1's optimum is the uniform point whenever C's rows have equal sums (e.g. C near the identity, gradients
    nearly orthogonal), so weights that stay uniform say how the memories' gradients relate, not that the solver
    did nothing."""

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        if self.early_stop_scale is None:  # the records of every sleep measured against its window stay as they were
            del out["early_stop_scale"]
        return out

    def summary(self) -> dict[str, Any]:
        """Compact view for logs and results tables."""
        last = lambda rows: rows[-1] if rows else None  # noqa: E731
        first = lambda rows: rows[0] if rows else None  # noqa: E731
        return {
            "skills": self.skills,
            "stop_iteration": self.stop_iteration,
            "stop_reason": self.stop_reason,
            "anchor_lambda": self.anchor_lambda,
            "final_alpha": last(self.alpha),
            "initial_memory_losses": first(self.memory_losses),
            "final_memory_losses": last(self.memory_losses),
            "skipped_steps": len(self.skipped_steps),
            "solver_status": dict(self.solver_status),
            **({} if self.early_stop_scale is None else {"early_stop_scale": self.early_stop_scale}),
        }


def cosine_matrix(gram: np.ndarray) -> list[list[float]]:
    """The cosine matrix of the gradients whose Gram matrix is ``gram`` (a zero gradient's row and column: 0)."""
    norms = np.sqrt(np.clip(np.diag(gram), 0.0, None))
    scale = np.where(norms > 0.0, norms, 1.0)
    cos = np.where(np.outer(norms, norms) > 0.0, gram / np.outer(scale, scale), 0.0)
    return [[float(x) for x in row] for row in cos]


def parameter_distance(params: Sequence[Tensor], reference: Sequence[Tensor]) -> float:
    """||theta - theta_ref||_2 over a list of parameter tensors."""
    if len(params) != len(reference):
        raise ValueError(f"parameter lists differ in length: {len(params)} vs {len(reference)}")
    total = 0.0
    with torch.no_grad():
        for p, r in zip(params, reference, strict=True):
            if p.shape != r.shape:
                raise ValueError(f"parameter shape {tuple(p.shape)} != reference shape {tuple(r.shape)}")
            total += float((p.detach() - r.to(p.device, p.dtype)).pow(2).sum())
    return math.sqrt(total)


def anchor_applies(strength: float, is_final_skill: bool, apply_after_final: bool) -> bool:
    """Whether Eq. 2's anchor can act in this sleep at all: a positive strength, and not the sleep after the final
    skill unless ``apply_after_final`` (paper, MT5: "The anchor is not applied after the final skill"). The one
    place the anchor's rule lives: :func:`anchor_coefficient` and ``sr-sleep``'s input checks both ask it."""
    return strength > 0.0 and (not is_final_skill or apply_after_final)


def anchor_gate_decides(config: SleepConfig, is_final_skill: bool) -> bool:
    """Whether the gate of Eq. 2 (``anchor_tau``) decides this sleep's anchor, so the gate snapshots theta_i^wake are
    needed: the anchor applies (:func:`anchor_applies`) and ``anchor_tau`` is set (``None``: always on)."""
    return (anchor_applies(config.anchor_strength, is_final_skill, config.anchor_after_final)
            and config.anchor_tau is not None)


def anchor_coefficient(
    params: Sequence[Tensor],
    wake_snapshots: Sequence[Sequence[Tensor]],
    strength: float,
    tau: float | None,
    is_final_skill: bool = False,
    apply_after_final: bool = False,
) -> tuple[float, list[float]]:
    """Eq. 2: lambda_k = lambda if min_{i<k} ||theta - theta_i^wake|| < tau else 0.

    Returns ``(lambda_k, [c_i])``. ``tau=None`` disables the gate (lambda always); no anchor after the
    final skill unless ``apply_after_final`` (paper, MT5: "The anchor is not applied after the final skill").
    """
    distances = [parameter_distance(params, snap) for snap in wake_snapshots]
    if not anchor_applies(strength, is_final_skill, apply_after_final):
        return 0.0, distances
    if tau is None:
        return float(strength), distances
    if not distances:
        return 0.0, distances
    return (float(strength) if min(distances) < tau else 0.0), distances


def _write_flat(grads: Sequence[Tensor | None], params: Sequence[Tensor], out: Tensor) -> None:
    """Write per-parameter gradients, flattened and concatenated, into ``out`` (P, or k x P for gradients batched
    over k losses); a parameter without a gradient gets zeros."""
    lead = out.shape[:-1]
    if all(g is not None for g in grads):
        torch.cat([g.reshape(*lead, -1) for g in grads], dim=-1, out=out)
        return
    offset = 0
    for p, g in zip(params, grads, strict=True):
        n = p.numel()
        if g is None:
            out[..., offset : offset + n].zero_()
        else:
            out[..., offset : offset + n].copy_(g.reshape(*lead, n))
        offset += n


def _flat_grads(loss: Tensor, params: Sequence[Tensor], out: Tensor) -> None:
    """Write d loss / d params, flattened, into ``out`` (P)."""
    _write_flat(torch.autograd.grad(loss, params, allow_unused=True), params, out)


def _flat_batched_grads(losses: Tensor, params: Sequence[Tensor], out: Tensor) -> None:
    """Write d losses[i] / d params, flattened, into row i of ``out`` (k x P) with one backward pass batched over the
    k one-hot cotangents."""
    cotangents = torch.eye(len(losses), device=losses.device, dtype=losses.dtype)
    _write_flat(torch.autograd.grad(losses, params, grad_outputs=cotangents, is_grads_batched=True,
                                    allow_unused=True), params, out)


def _memory_gradients(memories: Sequence[Memory], policy: Any, batches: Sequence[Any], params: Sequence[Tensor],
                      jac: Tensor, joint_forward: bool) -> Tensor:
    """Step 1 of an iteration: each memory's loss L_i on its batch and its gradient g_i as row i of ``jac``; returns
    the k losses (detached). ``joint_forward``: one forward per memory kind on the concatenated batches, then one
    backward batched over the k losses (autograd vmapped over the k one-hot cotangents): a few larger kernels
    instead of k passes' many. A non-finite loss gives a non-finite row, caught by the caller."""
    if joint_forward:
        stacked = torch.stack(per_memory_losses(memories, policy, batches))
        _flat_batched_grads(stacked, params, jac)
        return stacked.detach()
    loss_list = []
    for memory, batch, row in zip(memories, batches, jac, strict=True):
        loss = memory.loss(policy, batch)
        _flat_grads(loss, params, row)
        loss_list.append(loss.detach())
    return torch.stack(loss_list)


def _to_host(jac: Tensor, loss_values: Tensor, params: Sequence[Tensor], anchor_params: Sequence[Tensor] | None,
             lam: float) -> tuple[np.ndarray, list[float], float, list[Tensor] | None]:
    """Step 2: the iteration's one device-to-host copy (no stall between the k backward passes on a GPU): the k x k
    Gram matrix G = J J^T for the host's solver, the k losses, and with the anchor (lam > 0) the squared distance
    ||theta - theta_anchor||^2 for the record. Returns (G, losses, squared distance, theta - theta_anchor)."""
    k = jac.shape[0]
    diffs = None
    with torch.no_grad():
        parts = [(jac @ jac.T).reshape(-1), loss_values.reshape(-1)]
        if lam > 0.0:
            diffs = torch._foreach_sub(params, anchor_params)
            parts.append(torch.stack(torch._foreach_norm(diffs)).pow(2).sum().reshape(1))
        host = torch.cat([part.double() for part in parts]).cpu().numpy()
    gram = host[: k * k].reshape(k, k)
    losses = [float(x) for x in host[k * k : k * k + k]]
    return gram, losses, float(host[-1]) if lam > 0.0 else 0.0, diffs


def _nonfinite_memories(gram: np.ndarray, losses: Sequence[float], skills: Sequence[str]) -> list[str]:
    """Step 3: the memories whose loss or gradient is not finite (a NaN or Inf anywhere in g_i makes
    ||g_i||^2 = G_ii non-finite: one check on k numbers, not k x P)."""
    finite_rows = np.isfinite(losses) & np.isfinite(np.diag(gram))
    return [skills[i] for i in range(len(skills)) if not finite_rows[i]]


def _update_direction(weights: np.ndarray, jac: Tensor, params: Sequence[Tensor],
                      regularizer: Callable[[Sequence[Tensor]], Tensor] | None, lam: float,
                      diffs: Sequence[Tensor] | None) -> tuple[list[Tensor], float]:
    """Step 5: the update direction d = sum_i alpha_i g_i (the bargaining weights on the memories' gradients, Eq. 1),
    plus the regularizer's gradient (not bargained) and the anchor's lam (theta - theta_anchor) (Eq. 2), split into
    the parameters' shapes. Returns (per-parameter gradients, the regularizer's value)."""
    direction = torch.as_tensor(weights, dtype=jac.dtype, device=jac.device) @ jac
    grads = [g.view_as(p) for g, p in zip(torch.split(direction, [p.numel() for p in params]), params, strict=True)]
    reg_value = 0.0
    if regularizer is not None:
        reg = regularizer(params)
        reg_value = float(reg.detach())
        reg_grads = torch.autograd.grad(reg, params, allow_unused=True)
        grads = [g if r is None else g + r for g, r in zip(grads, reg_grads, strict=True)]
    if lam > 0.0:
        with torch.no_grad():
            torch._foreach_add_(grads, diffs, alpha=lam)
    return grads, reg_value


def _plateaued(history: Sequence[float], config: SleepConfig, scale: float | None = None) -> bool:
    """Step 7: the early stop (Table 6): every ``early_stop_window`` iterations, the mean objective of the last window
    against the one before changed by less than ``early_stop_tol`` (relative to the previous window's mean, or
    absolute; with ``scale``, relative to it: :attr:`SleepConfig.early_stop_scale`)."""
    window = config.early_stop_window
    if len(history) < 2 * window or len(history) % window:
        return False
    cur, prev = float(np.mean(history[-window:])), float(np.mean(history[-2 * window : -window]))
    if scale is not None:
        change = abs(cur - prev) / max(scale, 1e-12)
    else:
        change = abs(cur - prev) / max(abs(prev), 1e-12) if config.early_stop_relative else abs(cur - prev)
    return change < config.early_stop_tol


def _newest_guard_stops(losses: Sequence[Sequence[float]], config: SleepConfig) -> bool:
    """The newest-skill guard (:attr:`SleepConfig.newest_guard`): at the end of each early-stop window, whether the
    newest memory's window-mean loss has reached the mean of the older memories' window-mean losses."""
    window = config.early_stop_window
    if not config.newest_guard or len(losses) % window or len(losses[0]) < 2:
        return False
    means = np.mean(np.asarray(losses[-window:], dtype=np.float64), axis=0)
    return bool(means[-1] >= means[:-1].mean())


def memory_scale(memories: Sequence[Memory], policy: Any, seed: int) -> float:
    """The mean of the memories' own scales (:meth:`Memory.scale`) for ``policy`` now, drawn from ``seed``: what
    ``early_stop_scale=memory_scale`` measures the plateau rule against."""
    generator = torch.Generator().manual_seed(int(seed) % (2**63) + 7)
    with torch.no_grad():
        return float(np.mean([m.scale(policy, generator) for m in memories]))


def sleep_consolidate(
    params: Sequence[torch.nn.Parameter],
    policy: Any,
    memories: Sequence[Memory],
    config: SleepConfig,
    anchor_params: Sequence[Tensor] | None = None,
    wake_snapshots: Sequence[Sequence[Tensor]] = (),
    is_final_skill: bool = False,
    step_callback: Callable[[int], None] | None = None,
    aggregator: Aggregator | None = None,
    progress: bool = True,
    on_iteration: Callable[[int, dict[str, Any]], None] | None = None,
    regularizer: Callable[[Sequence[Tensor]], Tensor] | None = None,
) -> SleepResult:
    """Run one sleep phase in place on ``params`` (Algorithm 1, lines 7-15).

    Each iteration, in named steps: (1) every memory's loss and gradient on a fresh batch
    (:func:`_memory_gradients`); (2) the Gram matrix and losses to the host (:func:`_to_host`); (3) a step with a
    non-finite loss or gradient is skipped (:func:`_nonfinite_memories`); (4) the bargaining weights from the Gram
    matrix (the aggregator, Eq. 1); (5) the update direction with the anchor (:func:`_update_direction`, Eq. 2);
    (6) the Adam step, then the record; (7) the plateau check (:func:`_plateaued`); (8) with ``newest_guard``, the
    newest-skill guard (:func:`_newest_guard_stops`).

    Args:
        params: the shared policy's trainable parameters theta (updated in place).
        policy: what the memories evaluate (passed to :meth:`Memory.loss`).
        memories: the frozen memories M_1..M_k.
        config: sleep hyperparameters.
        anchor_params: theta_{k-1}^sleep, the previous consolidated checkpoint (same order as ``params``);
            ``None`` disables the anchor.
        wake_snapshots: theta_i^wake for i < k, for the gate of Eq. 2.
        is_final_skill: this is the sleep after the stream's last skill.
        step_callback: called with the iteration index after each applied update (e.g. excitability).
        aggregator: reuse an aggregator (keeps its warm start); default: a fresh one from ``config``.
        progress: show a tqdm progress bar.
        on_iteration: called after each applied update with the iteration index and that iteration's record
            (``objective``, ``memory_losses``, ``alpha``, ``grad_norms``, ``anchor_lambda``, ``solver_status``,
            ``solver_iterations``), e.g. to write the run log (``sr_imitation.infra.runlog``).
        regularizer: an extra differentiable term R(theta) of the objective whose gradient is added to the
            aggregated direction, like the anchor's (not bargained); e.g. Progress & Compress's EWC penalty during
            its compression. ``None`` (SR): nothing is added.
    """
    params = [p for p in params if p.requires_grad]
    if not params:
        raise ValueError("sleep needs at least one trainable parameter")
    if not memories:
        raise ValueError("sleep needs at least one memory")
    k = len(memories)
    skills = [m.skill for m in memories]
    device = params[0].device
    aggregator = aggregator or config.make_aggregator()

    if anchor_params is not None:
        anchor_params = [a.detach().to(p.device, p.dtype) for a, p in zip(anchor_params, params, strict=True)]
        lam, distances = anchor_coefficient(
            params, wake_snapshots, config.anchor_strength, config.anchor_tau, is_final_skill,
            config.anchor_after_final,
        )
    else:
        lam, distances = 0.0, [parameter_distance(params, s) for s in wake_snapshots]

    generator = torch.Generator().manual_seed(config.seed)
    # fused where torch has the kernel (CPU, CUDA); another device (MPS, the meta device of tests) takes foreach
    optimizer = torch.optim.Adam(params, lr=config.lr, fused=device.type in ("cpu", "cuda"))
    jac = torch.zeros(k, sum(p.numel() for p in params), device=device, dtype=params[0].dtype)
    result = SleepResult(skills, lam, distances, stop_iteration=0, stop_reason="max_iterations")
    scale = memory_scale(memories, policy, config.seed) if config.early_stop_scale == "memory_scale" else None
    if scale is not None:
        result.early_stop_scale = scale
        logger.info("plateau rule measured against the memories' scale %.4g", scale)
    consecutive_bad = 0
    bar = Progress(config.max_iterations, f"sleep k={k}", logger, enabled=progress)
    logger.info("sleep over %s: lambda=%g (distances %s), %s", skills, lam,
                [round(d, 3) for d in distances], aggregator)
    for it in range(config.max_iterations):
        bar.update(1)
        batches = [memory.sample(config.batch_size, generator) for memory in memories]
        loss_values = _memory_gradients(memories, policy, batches, params, jac, config.joint_forward)  # (1)
        gram, losses, anchor_term, diffs = _to_host(jac, loss_values, params, anchor_params, lam)  # (2)
        bad = _nonfinite_memories(gram, losses, skills)  # (3)
        if bad:
            result.skipped_steps.append({"iteration": it, "memories": bad})
            consecutive_bad += 1
            logger.warning("sleep iteration %d: non-finite loss or gradient from %s; step skipped", it, bad)
            if consecutive_bad >= config.max_nonfinite_steps:
                result.stop_iteration, result.stop_reason = it, "nonfinite"
                raise NonFiniteSleepError(
                    f"{consecutive_bad} consecutive sleep steps with non-finite losses/gradients from {bad}; "
                    "the policy was not updated by them"
                )
            continue
        consecutive_bad = 0
        gram = 0.5 * (gram + gram.T)  # float32 GEMM is not exactly symmetric
        agg = aggregator(gram)  # (4)
        grads, reg_value = _update_direction(agg.weights, jac, params, regularizer, lam, diffs)  # (5)
        for p, g in zip(params, grads, strict=True):  # (6)
            p.grad = g
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if step_callback is not None:
            step_callback(it)

        alpha = agg.alpha
        objective = float(np.dot(alpha, losses)) + 0.5 * lam * anchor_term + reg_value
        if not result.cosines_first_last:
            result.cosines_first_last = [cosine_matrix(gram)]
        last_gram = gram
        result.alpha.append([float(a) for a in alpha])
        result.grad_norms.append([float(x) for x in np.sqrt(np.clip(np.diag(gram), 0, None))])
        result.memory_losses.append(losses)
        result.sleep_objective.append(objective)
        result.solver_iterations.append(int(agg.iterations))
        result.solver_status[agg.status] = result.solver_status.get(agg.status, 0) + 1
        if on_iteration is not None:
            on_iteration(it, {"objective": objective, "memory_losses": losses, "alpha": result.alpha[-1],
                              "grad_norms": result.grad_norms[-1], "anchor_lambda": lam,
                              "solver_status": agg.status, "solver_iterations": int(agg.iterations)})
        result.stop_iteration = it + 1
        if progress and it % 10 == 0:
            bar.set_postfix(obj=f"{objective:.4g}", worst=f"{max(losses):.4g}")
        if _plateaued(result.sleep_objective, config, scale):  # (7)
            result.stop_reason = "plateau"
            break
        if _newest_guard_stops(result.memory_losses, config):  # (8) off unless newest_guard
            result.stop_reason = "newest_guard"
            break
    bar.close()
    if result.cosines_first_last:  # the last applied iteration's matrix, made once here rather than every iteration
        result.cosines_first_last.append(cosine_matrix(last_gram))
    logger.info("sleep stopped at iteration %d (%s); final memory losses %s", result.stop_iteration,
                result.stop_reason, result.memory_losses[-1] if result.memory_losses else None)
    return result
