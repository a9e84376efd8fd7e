"""``--policy.sleep=true`` on stock ``lerobot-train``: the ACT-SR policy keeps a uniform reservoir
of the observations it trains on and writes the skill's frozen actor memory beside each checkpoint, in the stream's
format; with ``sleep`` false or not given nothing changes. The flag on stock ``lerobot-train`` itself (a real
subprocess) is checked by the stock route's test (tests/substrates/act/test_sleep_statistics.py), whose first run is
that command."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_policy, make_pre_post_processors

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from lerobot_policy_act_sr.configuration_act_sr import DEFAULT_SLEEP_MEMORY_SIZE
from lerobot_policy_act_sr.modeling_act_sr import MEMORY_FILE, MEMORY_SNAPSHOT, ObservationReservoir
from sr_imitation.core.memory import load_memory
from sr_imitation.substrates.act.substrate import normalize_raw_observations
from tests.substrates.act.helpers import IMAGE, tiny_policy
from tests.substrates.act.test_policy import _features

SKILL = "approach"
REPO_ID = f"local/sr_needle_{SKILL}"  # what tests.substrates.act.helpers.make_skill_dataset names it
IMAGE_KEY = "observation.images.wrist"


def test_the_reservoir_is_a_uniform_seeded_sample():
    n, size, trials = 20, 5, 2000
    stream = torch.arange(n, dtype=torch.float32).unsqueeze(1)
    counts = torch.zeros(n)
    for seed in range(trials):
        reservoir = ObservationReservoir(size, seed=seed)
        for start in range(0, n, 3):  # uneven batches: 3, 3, ..., 2
            reservoir.add({"x": stream[start : start + 3]})
        held = reservoir.observations()["x"].squeeze(1).long()
        assert len(held) == size and len(set(held.tolist())) == size and reservoir.seen == n
        counts[held] += 1
    expected = trials * size / n  # each observation is held with probability size / n
    sd = (trials * (size / n) * (1 - size / n)) ** 0.5
    assert (counts - expected).abs().max() < 5 * sd, counts

    def run(seed: int) -> torch.Tensor:
        reservoir = ObservationReservoir(size, seed=seed)
        for start in range(0, n, 4):
            reservoir.add({"x": stream[start : start + 4], "u": stream[start : start + 4].to(torch.uint8)})
        out = reservoir.observations()
        assert out["u"].dtype == torch.uint8 and torch.equal(out["u"].float(), out["x"])  # rows stay together
        return out["x"]

    assert torch.equal(run(3), run(3)) and not all(torch.equal(run(3), run(s)) for s in range(4, 8))
    few = ObservationReservoir(size)
    few.add({"x": stream[:3]})
    assert len(few) == 3 and torch.equal(few.observations()["x"], stream[:3])  # fewer seen than size: all kept
    with pytest.raises(ValueError, match="reservoir holds"):
        few.add({"y": stream[:1]})


def test_the_memory_size_setting():
    assert ACTSRConfig(device="cpu").resolved_sleep_memory_size == DEFAULT_SLEEP_MEMORY_SIZE == 1024
    assert ACTSRConfig(device="cpu", sleep=True, sleep_memory_size=7).resolved_sleep_memory_size == 7
    with pytest.raises(ValueError, match="policy.sleep_memory_size must be >= 1"):
        ACTSRConfig(device="cpu", sleep=True, sleep_memory_size=0)
    for sleep in (None, False):  # a size without the switch would do nothing: the policy refuses it
        with pytest.raises(ValueError, match="policy.sleep_memory_size sizes the memory that policy.sleep=true"):
            ACTSRPolicy(_features(tiny_policy(sleep=sleep, sleep_memory_size=8)))


def _policy(dataset_root: Path, **overrides) -> tuple[ACTSRPolicy, object, LeRobotDataset]:
    """What lerobot-train builds: the policy from the dataset's metadata and the preprocessor with its stats."""
    dataset = LeRobotDataset(REPO_ID, root=dataset_root / SKILL, delta_timestamps={"action": [i / 10 for i in
                                                                                               range(4)]})
    torch.manual_seed(0)
    policy = make_policy(tiny_policy(**overrides), ds_meta=dataset.meta)
    pre, _ = make_pre_post_processors(policy.config, dataset_stats=dataset.meta.stats)
    return policy, pre, dataset


def _train(policy: ACTSRPolicy, pre, dataset: LeRobotDataset, steps: int = 5) -> list[dict[str, torch.Tensor]]:
    """``steps`` ACT-SR training steps as lerobot-train's loop takes them; returns the gradients of each."""
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, shuffle=True,
                                         generator=torch.Generator().manual_seed(0))
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    policy.train()
    grads = []
    for _, batch in zip(range(steps), loader, strict=False):
        loss, _ = policy.forward(pre(batch))
        optimizer.zero_grad()
        loss.backward()
        grads.append({n: p.grad.clone() for n, p in policy.named_parameters() if p.grad is not None})
        optimizer.step()
    return grads


def test_without_sleep_nothing_changes(image_datasets, tmp_path):
    runs = {}
    for sleep in (None, False, True):
        policy, pre, dataset = _policy(image_datasets, sleep=sleep, sleep_memory_size=8 if sleep else None)
        runs[sleep] = (_train(policy, pre, dataset), policy)
        assert (policy.reservoir is None) == (not sleep)
        policy.save_pretrained(tmp_path / str(sleep))
        assert (tmp_path / str(sleep) / MEMORY_FILE).exists() == bool(sleep)
    for sleep in (False, True):  # the same training, bit for bit: the reservoir draws from its own generator
        for a, b in zip(runs[None][0], runs[sleep][0], strict=True):
            assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        assert runs[None][1].state_dict().keys() == runs[sleep][1].state_dict().keys()


def test_sleep_writes_the_skill_s_frozen_actor_memory_which_loads_back(image_datasets, tmp_path):
    policy, pre, dataset = _policy(image_datasets, sleep=True, sleep_memory_size=8)
    policy.save_pretrained(tmp_path / "before")  # no training observation yet: nothing to remember
    assert not (tmp_path / "before" / MEMORY_FILE).exists()
    _train(policy, pre, dataset, steps=5)
    assert policy.reservoir.seen == 20 and len(policy.reservoir) == 8
    policy.save_pretrained(tmp_path / "ckpt")
    memory = load_memory(tmp_path / "ckpt" / MEMORY_FILE, skill=REPO_ID)  # the stream's loader
    assert isinstance(memory, ActorMemory) and memory.size == 8
    assert dict(memory.config) == {"reduction": "mean", "snapshot": MEMORY_SNAPSHOT}
    obs = memory.observations()
    assert set(obs) == {"observation.state", IMAGE_KEY}
    assert obs[IMAGE_KEY].dtype == torch.uint8 and obs[IMAGE_KEY].shape == (8, 3, IMAGE, IMAGE)
    assert memory.tensors["target"].shape == (8, 4, 7)
    # Raw observations, as the stream's memories hold them: every row is a frame of the dataset, images bit-exact.
    frames = [dataset.hf_dataset[i] for i in range(len(dataset.hf_dataset))]
    states = torch.stack([torch.as_tensor(f["observation.state"]) for f in frames])
    for state, image in zip(obs["observation.state"], obs[IMAGE_KEY], strict=True):
        match = torch.nonzero(torch.isclose(states, state, atol=1e-5).all(dim=1)).flatten()
        assert len(match) == 1, state
        assert torch.equal(image, (dataset[int(match)][IMAGE_KEY] * 255).round().to(torch.uint8))
    # The targets are the saved checkpoint's chunks on those observations, normalized as a sleep normalizes them.
    loaded = ACTSRPolicy.from_pretrained(tmp_path / "ckpt")
    loaded_pre, _ = make_pre_post_processors(loaded.config, dataset_stats=dataset.meta.stats)

    assert memory.verify_targets(lambda raw: loaded.action_chunk(normalize_raw_observations(loaded_pre, raw)),
                                 atol=1e-5) <= 1e-5
    # A policy built without dataset statistics cannot recover raw observations: refused at the first step.
    bare = ACTSRPolicy(policy.config)
    bare.train()
    with pytest.raises(ValueError, match="dataset statistics"):
        bare.forward(pre(next(iter(torch.utils.data.DataLoader(dataset, batch_size=2)))))
