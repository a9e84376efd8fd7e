"""What every ``sr-train`` configuration shares, whatever its substrate.

Both substrates' run configurations (:class:`sr_imitation.imitation.stream.TrainStreamConfig` for ACT,
:class:`sr_imitation.rl.config.RLTrainConfig` for SAC) use the same flag names for the same concepts::

    --substrate        act | sac (the key ``sr-train`` dispatches on; stored in the run's config)
    --method           the continual method (sr_imitation.stream.methods)
    --stream.*         the skills (--stream.skills), --stream.extend_from
    --sleep.*          the core's SleepConfig: --sleep.enabled, --sleep.lr, --sleep.aggregator, --sleep.anchor_*
    --memory.*         how skill memories are built: --memory.buffer_size
    --eval.*           evaluation: --eval.episodes, --eval.videos_per_skill, ...
    --wake.*           the wake budget and early stopping
    --seed --output_dir --resume --overwrite --progress --wandb.*

:func:`check_shared_settings` validates what they share; :data:`RENAMED_FLAGS` turns the flags of earlier versions
into a one-line hint.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

RENAMED_FLAGS: dict[str, str] = {
    "--policy.sleep": "--sleep.enabled",
    "--policy.sleep_lr": "--sleep.lr",
    "--policy.sleep_max_iterations": "--sleep.max_iterations",
    "--policy.sleep_batch_size": "--sleep.batch_size",
    "--policy.sleep_early_stop_tol": "--sleep.early_stop_tol",
    "--policy.sleep_early_stop_window": "--sleep.early_stop_window",
    "--policy.sleep_fw_iterations": "--sleep.fw_iterations",
    "--policy.grad_norm_eps": "--sleep.eps",
    "--policy.anchor_strength": "--sleep.anchor_strength",
    "--policy.anchor_tau": "--sleep.anchor_tau",
    "--policy.anchor_after_final": "--sleep.anchor_after_final",
    "--policy.aggregator": "--sleep.aggregator",
    "--policy.memory_buffer_size": "--memory.buffer_size",
    "--eval.n_episodes": "--eval.episodes",
    "--sleep_enabled": "--sleep.enabled",
    "--skills": "--stream.skills",
    "--extend_from": "--stream.extend_from",
}
"""Flags of earlier versions -> their name now (``sr-train`` answers an old flag with this hint instead of
draccus' generic error)."""


def renamed_flag_hint(args: list[str]) -> str | None:
    """A one-line hint for the first renamed flag in ``args`` (``None`` if there is none)."""
    for arg in args:
        name = arg.split("=", 1)[0]
        if name in RENAMED_FLAGS:
            return f"{name} was renamed: use {RENAMED_FLAGS[name]} (the same name on every substrate)"
    return None


def renamed_key_hint(config: Any, prefix: str = "") -> str | None:
    """:func:`renamed_flag_hint` for the keys of a config file's JSON tree (``{"policy": {"sleep_lr": ...}}``);
    an ``sr-main`` preset's ``train`` section is read as the run's config."""
    if not isinstance(config, dict):
        return None
    for key, value in config.items():
        dotted = f"{prefix}{key}" if prefix or key != "train" else ""
        if dotted and f"--{dotted}" in RENAMED_FLAGS:
            return (f"config key {dotted!r} was renamed: use {RENAMED_FLAGS['--' + dotted][2:]!r} "
                    f"(the same name on every substrate)")
        found = renamed_key_hint(value, f"{dotted}." if dotted else "")
        if found is not None:
            return found
    return None


def check_choices(key: str, given: Sequence[str], known: Iterable[str]) -> None:
    """``ValueError`` naming ``key``, the unknown values and the valid ones, unless every value of ``given`` is
    one of ``known`` (the experiment drivers' variant and option lists)."""
    known = list(known)
    unknown = [v for v in given if v not in known]
    if unknown:
        raise ValueError(f"{key}: unknown {unknown}; choose from {sorted(known)}")


def check_shared_settings(cfg: Any, substrate: str) -> None:
    """Refuse a configuration of another substrate and a hand-set ``sleep.seed`` (set per stage from ``--seed``).
    Raises ``ValueError`` naming the key."""
    if cfg.substrate != substrate:
        raise ValueError(f"substrate: this configuration is for {substrate!r}, got {cfg.substrate!r}")
    if cfg.sleep.seed != 0:
        raise ValueError("sleep.seed: set per stage from --seed by the substrate; leave it 0 and change --seed")
    if cfg.resume and cfg.overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
