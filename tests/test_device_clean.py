"""The hot paths run on a device that is not the CPU: each is run on PyTorch's ``meta`` device (tensors with shapes
and no data), where any tensor made on the CPU by mistake meets a meta tensor in an op and fails, as it would on CUDA.
A dispatch mode counts (and answers) what must leave the device: ``.item()``/``float()`` of a device scalar and
copies to the host. Each hot path's count is pinned: a new host round trip on it fails here, before anyone has a GPU
to find it on (``python -m sr_imitation.benchmarks.device`` then times them on a GPU)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch
from lerobot.utils.logging_utils import AverageMeter, MetricsTracker
from torch.utils._python_dispatch import TorchDispatchMode

from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.benchmarks.device import STATE_DIM, act_batch, act_policy
from sr_imitation.core.excitability import ExcitabilityConfig
from sr_imitation.core.sleep import sleep_consolidate
from sr_imitation.envs.metaworld.tasks import ACT_DIM, OBS_DIM
from sr_imitation.stream.config import StreamSleepConfig
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.wake import _NoHooks, hooked_update
from sr_imitation.substrates.sac.config import SACConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent

META = torch.device("meta")


class HostTraffic(TorchDispatchMode):
    """Counts what leaves the meta device and answers it with zeros: ``item`` (a scalar read by the host) and
    ``to_host`` (a tensor copied to the CPU)."""

    def __init__(self) -> None:
        super().__init__()
        self.count: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        source = args[0] if args and isinstance(args[0], torch.Tensor) else None
        if source is not None and source.device == META:
            if func is torch.ops.aten._local_scalar_dense.default:
                self.count["item"] += 1
                return True if source.dtype == torch.bool else 0  # "all finite", "all valid"
            if func is torch.ops.aten._to_copy.default and torch.device(kwargs.get("device", META)).type == "cpu":
                self.count["to_host"] += 1
                return torch.zeros(source.shape, dtype=kwargs.get("dtype") or source.dtype)
        return func(*args, **kwargs)


def _per_call(run, calls: int) -> dict[str, float]:
    """Host traffic per call of ``run`` (called ``calls`` times after one uncounted call: optimizer state)."""
    with HostTraffic():
        run()
    with HostTraffic() as traffic:
        for _ in range(calls):
            run()
    return {k: v / calls for k, v in traffic.count.items()}


def test_an_act_wake_step_stays_on_the_device_but_for_four_numbers():
    policy = act_policy(torch.device("cpu"), vision=False).to(META)
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    batch = act_batch(8, False, META)
    tracker = MetricsTracker(8, 100, 100, {"loss": AverageMeter("loss"), "grad_norm": AverageMeter("grdn"),
                                           "lr": AverageMeter("lr"), "update_s": AverageMeter("updt_s")})
    traffic = _per_call(lambda: hooked_update(tracker, policy, dict(batch), optimizer, 10.0, _NoHooks()), 3)
    # four numbers: the loss and gradient norm for the log (LeRobot's update_policy reads the same two), the l1
    # loss LeRobot's ACT puts in its output dict, ACT-SR's check that the loss is finite
    assert traffic == {"item": 4}
    assert all(p.device == META for p in policy.parameters())


@pytest.mark.parametrize("joint_forward", [False, True])
@pytest.mark.parametrize("substrate", ["act", "sac"])
def test_a_sleep_iteration_moves_the_k_losses_and_the_k_by_k_gram_to_the_host_in_one_copy(substrate, joint_forward):
    k = 3
    if substrate == "act":
        policy = act_policy(torch.device("cpu"), vision=False)
        g = torch.Generator().manual_seed(0)
        memories = [ActorMemory.from_observations(f"s{i}", lambda obs: torch.zeros(len(obs["observation.state"]), 16,
                                                                                   7),
                                                  {"observation.state": torch.randn(64, STATE_DIM, generator=g)})
                    for i in range(k)]
        policy.to(META)
        policy.set_observation_normalizer(lambda raw: {"observation.state": raw["observation.state"].to(META),
                                                       "observation.environment_state":
                                                           raw["observation.state"].to(META)})
        params, fn = [p for p in policy.parameters() if p.requires_grad], policy.memory_chunk
        cfg = SurgicAISleepConfig(max_iterations=4, early_stop_tol=0.0, batch_size=4, joint_forward=joint_forward)
    else:
        agent = SACAgent(SACConfig(hidden_dim=32), ExcitabilityConfig())
        agent.normalizer.update(np.random.default_rng(0).normal(size=(10, OBS_DIM)))
        memories = [CriticMemory.from_agent(f"s{i}", agent, np.random.default_rng(i).normal(size=(64, OBS_DIM)))
                    for i in range(k)]
        agent = SACAgent(SACConfig(hidden_dim=32), ExcitabilityConfig(), device=META)
        params, fn = agent.actor_parameters(), agent.policy_fn
        cfg = StreamSleepConfig.mt5(max_iterations=4, early_stop_tol=0.0, batch_size=4, anchor_tau=None,
                                    joint_forward=joint_forward)
    anchor = [p.detach().clone() for p in params]
    with HostTraffic() as traffic:
        result = sleep_consolidate(params, fn, memories, cfg, anchor_params=anchor, progress=False)
    iterations = result.stop_iteration
    assert iterations == 4 and all(p.device == META for p in params)
    # per iteration one copy to the host: the k x k Gram matrix for the host's Nash solver, the k memory losses and
    # the anchor's squared distance for the record; no scalar read between the k backward passes
    assert dict(traffic.count) == {"to_host": iterations}


def test_a_sac_update_stays_on_the_device_but_for_its_logged_numbers():
    rng = np.random.default_rng(0)
    replay = ReplayBuffer(256)
    for _ in range(256):
        replay.add(rng.normal(size=OBS_DIM), rng.uniform(-1, 1, ACT_DIM), 1.0, rng.normal(size=OBS_DIM), False)
    cfg = SACConfig(hidden_dim=32, batch_size=16)
    agent = SACAgent(cfg, ExcitabilityConfig(), device=META)
    agent.normalizer.update(replay.obs[:100])  # host observations (an environment's) into device statistics
    traffic = _per_call(lambda: agent.update(replay.batch(replay.indices(16, rng), META), 1e-3), 3)
    assert traffic == {"item": 6}  # the six numbers of UpdateInfo, for the log


def test_the_batched_per_memory_gradients_the_benchmark_times_are_the_sleep_s_gradients():
    from sr_imitation.benchmarks.per_memory_grads import per_memory_gradients

    r = per_memory_gradients(torch.device("cpu"), vision=False, repeats=1)
    assert r["loop"]["difference"] == 0 and all(m["ms"] > 0 and m["difference"] < 1e-4 for m in r.values())
    assert r["joint"]["ops"] < r["loop"]["ops"] / 2 and r["vmap"]["ops"] < r["loop"]["ops"] / 2  # batched passes


def test_the_per_memory_gradient_benchmark_at_the_presets_sizes_k_passes_scale_with_k_batched_ones_do_not():
    """--k / --batch (the state-only presets' sleeps: 2-5 memories of batch 32): the k passes' operations grow with k,
    the batched backward's stay, so its launch advantage shrinks at small k (the second GPU session's end-to-end
    finding)."""
    from sr_imitation.benchmarks.per_memory_grads import per_memory_gradients

    small = per_memory_gradients(torch.device("cpu"), vision=False, repeats=1, k=2, batch=4)
    large = per_memory_gradients(torch.device("cpu"), vision=False, repeats=1, k=4, batch=4)
    assert all(m["difference"] < 1e-4 for m in (*small.values(), *large.values()))
    assert large["loop"]["ops"] > 1.8 * small["loop"]["ops"]
    assert abs(large["joint"]["ops"] - small["joint"]["ops"]) < 0.05 * small["joint"]["ops"]
