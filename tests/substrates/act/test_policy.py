"""ACT-SR policy: LeRobot discovery, config defaults, save/load, wake distillation, actor memories."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import get_policy_class

from lerobot_policy_act_sr import ACTSRConfig, ACTSRPolicy
from lerobot_policy_act_sr.actor_memory import ActorMemory
from sr_imitation.core.memory import load_memory
from sr_imitation.substrates.act.config import SurgicAISleepConfig
from sr_imitation.substrates.act.trainer import TrainStreamConfig
from tests.substrates.act.helpers import ACTION_DIM, IMAGE, STATE_DIM, tiny_policy


def _features(cfg: ACTSRConfig, images: bool = True) -> ACTSRConfig:
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    if images:
        cfg.input_features["observation.images.wrist"] = PolicyFeature(FeatureType.VISUAL, (3, IMAGE, IMAGE))
    else:
        cfg.input_features["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (STATE_DIM,))
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}
    return cfg


def _batch(n: int = 4, images: bool = True, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = {"observation.state": torch.randn(n, STATE_DIM, generator=g),
           "action": torch.randn(n, 4, ACTION_DIM, generator=g), "action_is_pad": torch.zeros(n, 4, dtype=torch.bool)}
    if images:
        out["observation.images.wrist"] = torch.rand(n, 3, IMAGE, IMAGE, generator=g)
    return out


def test_paper_defaults_and_validation():
    cfg = ACTSRConfig(device="cpu")
    assert (cfg.chunk_size, cfg.latent_dim, cfg.kl_weight, cfg.vision_backbone) == (16, 32, 10.0, "resnet18")
    assert cfg.pretrained_backbone_weights is None  # nothing downloads at run time
    assert (cfg.optimizer_lr, cfg.optimizer_lr_backbone, cfg.optimizer_weight_decay) == (1e-4, 1e-5, 1e-4)
    assert [cfg.distill_weight(k) for k in (1, 2, 3, 5)] == [0.0, 1.0, 0.5, 0.5]
    # The stream's sleep and memory defaults are the SurgicAI table's (sr-train --sleep.* --memory.*).
    stream = TrainStreamConfig(policy=cfg)
    sleep = stream.sleep
    assert (sleep.lr, sleep.max_iterations, sleep.batch_size, sleep.fw_iterations) == (1e-5, 1000, 8, 5)
    assert (sleep.anchor_strength, sleep.early_stop_tol, stream.memory.buffer_size) == (1e-2, 1e-3, 1024)
    assert (sleep.anchor_tau, sleep.anchor_after_final, sleep.early_stop_window, sleep.enabled) == (None, True, 50,
                                                                                                   True)
    with pytest.raises(ValueError, match="aggregator"):
        SurgicAISleepConfig(aggregator="sum")
    with pytest.raises(ValueError, match="lr"):
        SurgicAISleepConfig(lr=0.0)
    for key in ("distill_weight_second", "distill_weight_later", "distill_batch_size"):
        with pytest.raises(ValueError, match=key):  # NaN is refused at parse time, not at the first wake
            ACTSRConfig(device="cpu", **{key: float("nan")})
    with pytest.raises(ValueError, match="mean_grad"):
        SurgicAISleepConfig(aggregator="mean")  # the old name, with a hint
    with pytest.raises(ValueError, match="sleep.seed"):
        TrainStreamConfig(policy=cfg, sleep=SurgicAISleepConfig(seed=3))


def test_sleep_defaults_survive_a_partial_flag():
    """draccus fills the fields a flag leaves out from the class defaults: --sleep.lr alone must keep the SurgicAI
    table's other values (not MT5's tau = 150 / 4000 iterations)."""
    from sr_imitation.substrates.act.cli import parse_config

    cfg = parse_config(TrainStreamConfig, None, ["--sleep.lr=1e-4"])
    assert cfg.sleep.lr == 1e-4
    assert (cfg.sleep.anchor_tau, cfg.sleep.max_iterations, cfg.sleep.batch_size) == (None, 1000, 8)


def test_lerobot_factory_finds_the_policy_and_draccus_parses_flags():
    assert get_policy_class("act_sr") is ACTSRPolicy
    code = (
        "import draccus\n"
        "from lerobot.configs.train import TrainPipelineConfig\n"
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "cfg = draccus.parse(TrainPipelineConfig, args=['--policy.type=act_sr', '--policy.distill_weight_later=0.25',\n"
        "    '--policy.device=cpu', '--dataset.repo_id=x/y'])\n"
        "assert type(cfg.policy).__name__ == 'ACTSRConfig' and cfg.policy.distill_weight_later == 0.25\n"
        "assert cfg.policy.type == 'act_sr'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_save_and_load_round_trip(tmp_path):
    policy = ACTSRPolicy(_features(tiny_policy(distill_weight_later=0.25)))
    policy.save_pretrained(tmp_path)
    cfg = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(cfg, ACTSRConfig) and cfg.type == "act_sr"
    assert cfg.distill_weight_later == 0.25
    loaded = ACTSRPolicy.from_pretrained(tmp_path, config=cfg)
    batch = _batch()
    torch.testing.assert_close(loaded.predict_action_chunk(batch), policy.predict_action_chunk(batch))


def test_action_chunk_is_deterministic_differentiable_and_keeps_the_mode():
    policy = ACTSRPolicy(_features(tiny_policy()))
    policy.train()
    batch = _batch()
    a, b = policy.action_chunk(batch), policy.action_chunk(batch)
    torch.testing.assert_close(a, b)
    assert a.shape == (4, 4, ACTION_DIM) and a.requires_grad and policy.training


def _memory_for(policy: ACTSRPolicy, seed: int) -> ActorMemory:
    obs = {k: v for k, v in _batch(16, seed=seed).items() if k.startswith("observation")}
    return ActorMemory.from_observations("approach", policy.memory_chunk, obs, snapshot="skill_1/wake")


def test_wake_distillation_adds_a_gradient_toward_the_snapshot():
    policy = ACTSRPolicy(_features(tiny_policy()))
    policy.set_observation_normalizer(lambda raw: {k: (v.float() / 255 if v.dtype == torch.uint8 else v)
                                                   for k, v in raw.items()})
    memory = _memory_for(policy, seed=1)
    assert memory.tensors["input.observation.images.wrist"].dtype == torch.uint8
    # The snapshot itself: zero distillation loss.
    assert memory.objective(policy.memory_chunk, 8).item() == pytest.approx(0.0, abs=1e-10)
    assert memory.verify_targets(policy.memory_chunk) < 1e-6
    with torch.no_grad():  # move away from the snapshot
        for p in policy.model.action_head.parameters():
            p.add_(0.5)
    with pytest.raises(ValueError, match="differ"):
        memory.verify_targets(policy.memory_chunk)
    policy.train()
    _, plain = policy.forward(_batch())
    policy.set_wake_memories([memory], weight=0.5, seed=0)
    loss, info = policy.forward(_batch())
    assert info["distill_loss"] > 0
    assert loss.item() == pytest.approx(info["bc_loss"] + 0.5 * info["distill_loss"], rel=1e-4)
    policy.zero_grad()
    distill_only = memory.objective(policy.memory_chunk, 8)
    distill_only.backward()
    assert policy.model.action_head.weight.grad.abs().sum() > 0
    assert "distill_loss" not in plain


def test_memory_reduction_mean_is_the_per_element_mean_of_the_squared_chunk_difference():
    policy = ACTSRPolicy(_features(tiny_policy()))
    policy.set_observation_normalizer(lambda raw: {k: (v.float() / 255 if v.dtype == torch.uint8 else v)
                                                   for k, v in raw.items()})
    obs = {k: v for k, v in _batch(16, seed=3).items() if k.startswith("observation")}
    mean = ActorMemory.from_observations("approach", policy.memory_chunk, obs)
    total = ActorMemory.from_observations("approach", policy.memory_chunk, obs, reduction="sum")
    assert mean.config["reduction"] == "mean" and total.config["reduction"] == "sum"
    with torch.no_grad():
        for p in policy.model.action_head.parameters():
            p.add_(0.1)
    batch = {k: v[:8] for k, v in mean.tensors.items()}
    chunk = policy.memory_chunk({k.removeprefix("input."): v for k, v in batch.items() if k.startswith("input.")})
    expected = (chunk - batch["target"]).pow(2).mean()
    assert mean.loss(policy.memory_chunk, batch).item() == pytest.approx(expected.item(), rel=1e-5)
    elements = chunk.shape[1] * chunk.shape[2]
    assert total.loss(policy.memory_chunk, batch).item() == pytest.approx(elements * expected.item(), rel=1e-5)
    with pytest.raises(ValueError, match="reduction"):
        ActorMemory.from_observations("approach", policy.memory_chunk, obs, reduction="max")
    with pytest.raises(ValueError, match="distill_reduction"):
        ACTSRConfig(device="cpu", distill_reduction="max")


def test_memories_of_different_skills_share_one_policy_call():
    """The stream writes each skill's memory with its own checkpoint's name (``config["snapshot"]``); that name is
    provenance, not part of the objective, so wake distillation (``summed_objective``) and the sleep's
    ``joint_forward`` evaluate all the memories in ONE forward pass, with the same losses as one pass each. Before
    2026-11-27 the name split them into groups of one: every pass stayed separate (the GPU finding in
    docs/BENCHMARKS.md). A memory with another reduction is a different objective and keeps its own call."""
    from sr_imitation.core.memory import per_memory_losses

    policy = ACTSRPolicy(_features(tiny_policy()))
    policy.set_observation_normalizer(lambda raw: {k: (v.float() / 255 if v.dtype == torch.uint8 else v)
                                                   for k, v in raw.items()})
    memories = [ActorMemory.from_observations(
        skill, policy.memory_chunk, {k: v for k, v in _batch(12, seed=i).items() if k.startswith("observation")},
        snapshot=f"skill_{i + 1}_{skill}/wake") for i, skill in enumerate(["approach", "place", "insert"])]
    with torch.no_grad():
        for p in policy.model.action_head.parameters():
            p.add_(0.1)
    calls = []

    def counted(obs):
        calls.append(len(next(iter(obs.values()))))
        return policy.memory_chunk(obs)

    gen = torch.Generator().manual_seed(0)
    batches = [m.sample(8, gen) for m in memories]
    joint = per_memory_losses(memories, counted, batches)
    assert calls == [24]  # one call on the three batches together
    separate = [m.loss(policy.memory_chunk, b) for m, b in zip(memories, batches, strict=True)]
    torch.testing.assert_close(torch.stack(joint), torch.stack(separate), rtol=1e-5, atol=1e-7)
    other = ActorMemory(memories[2].skill, dict(memories[2].tensors), {**memories[2].config, "reduction": "sum"})
    calls.clear()
    per_memory_losses([*memories[:2], other], counted, batches)
    assert sorted(calls) == [8, 16]


def test_memories_need_a_normalizer_and_non_finite_losses_fail_loudly():
    policy = ACTSRPolicy(_features(tiny_policy()))
    with pytest.raises(RuntimeError, match="normalizer"):
        policy.set_wake_memories([object()], 1.0)  # type: ignore[list-item]
    bad = _batch()
    bad["action"][0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="non-finite ACT-SR loss"):
        policy.forward(bad)


def test_actor_memory_file_round_trip(tmp_path):
    policy = ACTSRPolicy(_features(tiny_policy()))
    policy.set_observation_normalizer(lambda raw: {k: (v.float() / 255 if v.dtype == torch.uint8 else v)
                                                   for k, v in raw.items()})
    memory = _memory_for(policy, seed=2)
    loaded = load_memory(memory.save(tmp_path / "m.safetensors"), skill="approach")
    assert isinstance(loaded, ActorMemory) and loaded.fingerprint() == memory.fingerprint()
    assert loaded.kind == "act_actor"  # the kind every saved ACT memory file names: files written before still load
    assert loaded.config["snapshot"] == "skill_1/wake"
    assert loaded.verify_targets(policy.memory_chunk) < 1e-6


def test_state_only_mode_feeds_the_state_as_environment_state():
    policy = ACTSRPolicy(_features(tiny_policy(use_images=False), images=False))
    batch = _batch(images=False)
    chunk = policy.predict_action_chunk({k: v for k, v in batch.items() if k.startswith("observation")})
    assert chunk.shape == (4, 4, ACTION_DIM)
    policy.train()
    loss, _ = policy.forward(batch)
    assert torch.isfinite(loss)


def _backbone_feature_rms(policy: ACTSRPolicy, conv_scale: float) -> float:
    """RMS of the backbone's feature map after multiplying every conv weight by ``conv_scale`` (what weight
    growth during training does)."""
    with torch.no_grad():
        for module in policy.model.backbone.modules():
            if isinstance(module, torch.nn.Conv2d):
                module.weight.mul_(conv_scale)
        images = torch.rand(4, 3, IMAGE, IMAGE, generator=torch.Generator().manual_seed(0))
        return policy.model.backbone(images)["feature_map"].pow(2).mean().sqrt().item()


def test_a_backbone_without_pretrained_weights_is_group_normalized_and_keeps_its_feature_scale():
    """Without pretrained weights LeRobot's frozen batch norm normalizes nothing: the features grow geometrically
    with the conv weights (the CPU vision preset's image tokens reached RMS 95,000 and drowned the state token).
    GroupNorm makes the features invariant to that scale."""
    from torchvision.ops.misc import FrozenBatchNorm2d

    def norms(policy: ACTSRPolicy) -> set[type]:
        return {type(m) for m in policy.model.backbone.modules()} & {FrozenBatchNorm2d, torch.nn.GroupNorm}

    rms = {}
    for norm in ("auto", "group", "frozen_batch"):
        torch.manual_seed(0)
        policy = ACTSRPolicy(_features(tiny_policy(backbone_norm=norm)))
        assert norms(policy) == ({FrozenBatchNorm2d} if norm == "frozen_batch" else {torch.nn.GroupNorm})
        rms[norm] = (_backbone_feature_rms(policy, 1.0), _backbone_feature_rms(policy, 2.0))
    group, frozen = rms["group"], rms["frozen_batch"]
    assert group[1] == pytest.approx(group[0], rel=1e-3)
    assert frozen[1] > 100 * frozen[0]  # geometric: 2x per conv, 9 convs on the shortest path (measured 480x)
    assert rms["auto"] == rms["group"]
    assert ACTSRConfig(device="cpu", pretrained_backbone_weights="x").resolved_backbone_norm == "frozen_batch"
    with pytest.raises(ValueError, match="backbone_norm"):
        ACTSRConfig(device="cpu", backbone_norm="batch")
    # Trainable: the group norms' affine parameters are in the backbone's optimizer group.
    policy = ACTSRPolicy(_features(tiny_policy()))
    names = {n for n, _ in policy.named_parameters() if "backbone" in n}
    assert any(n.endswith("bn1.weight") for n in names)


def test_the_training_only_vae_encoder_is_all_that_the_deployed_parameters_leave_out():
    """Exactly the parameters no inference output depends on through a module the deployed policy runs: the VAE
    encoder gets no gradient from the action chunk; every excluded name belongs to it."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_policy_act_sr import ACTSRPolicy
    from tests.substrates.act.helpers import tiny_policy

    cfg = tiny_policy(use_images=False)
    cfg.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (6,)),
                          "observation.environment_state": PolicyFeature(FeatureType.ENV, (6,))}
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
    policy = ACTSRPolicy(cfg)
    policy.set_observation_normalizer(lambda raw: dict(raw))
    policy.memory_chunk({"observation.state": torch.randn(4, 6)}).sum().backward()
    deployed = {n for n, _ in policy.deployed_named_parameters()}
    excluded = {n for n, p in policy.named_parameters() if p.requires_grad} - deployed
    assert excluded and all(n.startswith("model.vae_encoder") for n in excluded)
    assert all(p.grad is None or not p.grad.any() for n, p in policy.named_parameters() if n in excluded)
    assert any(p.grad is not None and p.grad.any() for n, p in policy.named_parameters() if n in deployed)


@pytest.mark.parametrize("images", [True, False])
def test_chunk_and_features_returns_every_modality_and_the_encoder_output_in_one_pass(images):
    """M2Distill's features: the chunk equals action_chunk's, each modality's embedding and the encoder output are
    there, gradients reach the weights through them, and no hook is left behind."""
    policy = ACTSRPolicy(_features(tiny_policy(), images=images))
    batch = _batch(images=images)
    chunk, feats = policy.action_chunk_and_features(batch)
    assert torch.equal(chunk, policy.action_chunk(batch))
    modalities = {"camera0"} if images else {"env_state"}
    assert set(feats) == {"robot_state", "encoder"} | modalities
    tokens = 2 + (0 if images else 1)  # latent, robot state [, env state] + one token per feature-map cell
    if images:
        cells = feats["camera0"].shape[-2] * feats["camera0"].shape[-1]
        assert feats["camera0"].shape[0] == 4 and feats["encoder"].shape == (tokens + cells, 4, 32)
    else:
        assert feats["env_state"].shape == (4, 32) and feats["encoder"].shape == (tokens, 4, 32)
    sum(f.pow(2).mean() for f in feats.values()).backward()
    assert policy.model.encoder_robot_state_input_proj.weight.grad.abs().sum() > 0
    assert all(not m._forward_hooks for m in policy.model.modules())


def test_a_config_without_a_device_picks_one_quietly(caplog):
    """LeRobot answers ``device=None`` with a warning ("Device 'None' is not available. Switching to 'cpu'.") on every
    ``sr-train`` without a config; ACT-SR picks LeRobot's device order itself; a named, absent device still warns."""
    from lerobot_policy_act_sr.configuration_act_sr import default_device

    with caplog.at_level("WARNING"):
        cfg = ACTSRConfig()
    assert cfg.device == default_device() and not [r for r in caplog.records if "is not available" in r.getMessage()]
    if not torch.cuda.is_available():
        with caplog.at_level("WARNING"):
            assert ACTSRConfig(device="cuda").device == default_device()
        assert any("Device 'cuda' is not available" in r.getMessage() for r in caplog.records)
