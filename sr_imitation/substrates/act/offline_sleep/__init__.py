"""``sr-sleep``: consolidate an already deployed ACT-SR policy offline from saved skill memories.

    sr-sleep --policy.path=outputs/place/checkpoints/last/pretrained_model \\
        --memories=[outputs/approach/memory.safetensors,outputs/place/memory.safetensors] --output_dir=outputs/slept

One sleep phase of Algorithm 1 (lines 7-15; :func:`~sr_imitation.core.sleep.sleep_consolidate`: Nash-bargained
per-memory gradients, Eq. 1, with the gated proximal anchor of Eq. 2) with the ``--sleep.*`` settings of
``sr-train`` (defaults: the paper's SurgicAI table), on the deployed policy's parameters only and with each memory
evaluating the deployed action chunk, exactly as the stream's sleep does (both use
:func:`~sr_imitation.substrates.act.substrate.act_sleep_problem`).

The folder's modules: ``config`` (the command line), ``inputs`` (loading and checking every input before the first
gradient), ``run`` (the sleep and its loss checks), ``report`` (``sleep.json`` and ``sleep.md``). What it takes from
its inputs, what it checks and what it writes: docs/ARCHITECTURE.md, "sr-sleep: offline consolidation".
"""

from __future__ import annotations

from sr_imitation.substrates.act.offline_sleep.config import (  # noqa: F401  (the command's names, one place)
    DIAGNOSTICS_FILE,
    LOSS_BATCH,
    PRETRAINED_FILES,
    REPORT_FILE,
    RESULTS_FILE,
    RESULTS_FORMAT,
    RESULTS_VERSION,
    AnchorConfig,
    OfflineSleepConfig,
    PolicyPathConfig,
    SleepEvalConfig,
)
from sr_imitation.substrates.act.offline_sleep.inputs import (  # noqa: F401  (the command's names, one place)
    RUN_SEARCH_DEPTH,
    SLEEP_OUTPUT_ENTRIES,
    STAGE_REFERENCE,
    LoadedMemory,
    LoadedPolicy,
    MemoryFile,
    SleepInputs,
    _check_pretrained_dir,
    _inside,
    _load_state,
    _steps,
    check_eval_envs,
    check_inputs,
    check_memory_order,
    checkpoint_parameters,
    expected_observations,
    express_targets,
    load_actor_memory,
    load_policy,
    policy_run_skills,
    processor_stats,
    read_actor_memory,
    settle_statistics,
    sleep_output_problem,
    snapshot_directory,
)
from sr_imitation.substrates.act.offline_sleep.report import (  # noqa: F401  (the command's names, one place)
    _record,
    report_markdown,
)
from sr_imitation.substrates.act.offline_sleep.run import (  # noqa: F401  (the command's names, one place)
    ABSURD_LOSS,
    SleepFailedError,
    _evaluate,
    _per_element,
    _progress_logger,
    _stats_hint,
    check_losses,
    check_moved,
    memory_loss,
    run_offline_sleep,
)
