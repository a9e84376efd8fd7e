"""The baselines' distinctive mechanisms (issue: RL baselines on MT5), each able to fail: EWC's penalty and Fisher
normalization, A-GEM's projection, DER's stored targets, Nash-MTL / PCGrad acting during wake and never sleeping;
every method through the engine on the toy substrate, resumed after a kill to identical weights."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from sr_imitation.core.memory import OutputDistillationMemory, load_memory
from sr_imitation.stream import METHODS
from sr_imitation.stream.methods._gradients import current_grad, flat_grad, set_grad
from sr_imitation.stream.methods.agem import agem_project
from sr_imitation.stream.methods.ewc import FisherMemory
from tests.stream.conftest import KilledError, make_engine

pytestmark = pytest.mark.usefixtures("toy_methods")  # A-GEM, Nash-MTL and PCGrad on the toy too

BASELINES = ["ewc", "der", "agem", "clear", "nash_mtl", "pcgrad", "reset_distill", "progress_compress"]


@pytest.fixture(autouse=True)
def short_distillation(monkeypatch):
    """Tiny: 40 distillation steps of 16 states for Reset & Distill and P&C, not 2000 of 256."""
    for name in ("reset_distill", "progress_compress"):
        cls = METHODS[name]
        monkeypatch.setattr(cls, "config", dataclasses.replace(cls.config, iterations=40, batch_size=16))


def _params(seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(3, 2, generator=g, requires_grad=True), torch.randn(4, generator=g, requires_grad=True)]


def test_ewc_penalty_is_zero_at_the_anchor_and_grows_with_fisher_weighted_distance():
    params = _params()
    policy = torch.nn.Linear(2, 1)

    def log_likelihood(states, generator):  # a toy Gaussian in the two parameter tensors
        return -((states[:, :2] @ params[0].T).sum(1) + states[:, 2:] @ params[1]).pow(2)

    states = torch.randn(50, 6, generator=torch.Generator().manual_seed(1))
    memory = FisherMemory.estimate("a", params, log_likelihood, states, torch.Generator())
    fisher = [memory.tensors["fisher.000"], memory.tensors["fisher.001"]]
    assert torch.sqrt(sum(f.pow(2).sum() for f in fisher)) == pytest.approx(1.0, abs=1e-6)  # unit Frobenius
    assert all((f >= 0).all() for f in fisher)
    assert memory.penalty(params).item() == 0.0
    moved = [p.detach() + 0.1 for p in params]
    expected = sum((f * 0.01).sum() for f in fisher)
    assert memory.penalty(moved).item() == pytest.approx(float(expected), rel=1e-5)
    assert memory.penalty([p.detach() + 0.2 for p in params]).item() == pytest.approx(4 * float(expected), rel=1e-5)
    # a parameter with zero Fisher is free to move
    free = [p.detach().clone() for p in params]
    zero = (fisher[1] == 0).nonzero()
    if len(zero):
        free[1][zero[0]] += 5.0
        assert memory.penalty(free).item() == 0.0
    with pytest.raises(ValueError, match="protects 2 parameters"):
        memory.penalty(params[:1])
    del policy


def test_ewc_memory_roundtrips_and_its_bytes_are_its_tensors(tmp_path):
    params = _params()
    memory = FisherMemory.estimate("a", params, lambda s, g: (s @ params[1]).pow(2).neg() + 0 * params[0].sum(),
                                   torch.randn(8, 4), torch.Generator())
    loaded = load_memory(memory.save(tmp_path / "m.safetensors"), skill="a")
    assert isinstance(loaded, FisherMemory) and loaded.fingerprint() == memory.fingerprint()
    assert loaded.nbytes() == 2 * sum(p.numel() * 4 for p in params)


def test_agem_leaves_agreeing_gradients_and_makes_conflicting_ones_orthogonal_or_better():
    g = torch.Generator().manual_seed(0)
    for _ in range(200):
        grad, ref = torch.randn(7, generator=g), torch.randn(7, generator=g)
        out, conflicted = agem_project(grad, ref)
        if torch.dot(grad, ref) >= 0:
            assert not conflicted and torch.equal(out, grad)
        else:
            assert conflicted and torch.dot(out, ref) >= -1e-5
            # the smallest change that does it: only the component along ref is removed
            assert torch.allclose(out - grad, (out - grad).dot(ref) / ref.dot(ref) * ref, atol=1e-5)


def test_der_targets_are_the_outputs_at_storage_time():
    net = torch.nn.Linear(3, 2)
    states = torch.randn(20, 3)
    policy = lambda obs: net(obs["state"])  # noqa: E731
    memory = OutputDistillationMemory.from_snapshot("a", policy, {"state": states})
    assert torch.equal(memory.tensors["target"], net(states).detach())
    assert memory.loss(policy, dict(memory.tensors)).item() == 0.0
    with torch.no_grad():
        net.weight.add_(0.5)
    assert memory.loss(policy, dict(memory.tensors)).item() > 0.0
    assert torch.equal(memory.tensors["target"], memory.tensors["target"])  # frozen: the target did not follow


def test_flat_gradient_helpers_roundtrip():
    params = _params()
    flat = flat_grad(params[0].pow(2).sum() + params[1].sum(), params)
    assert params[0].grad is None  # untouched
    (params[0].pow(2).sum() + params[1].sum()).backward()
    assert torch.equal(current_grad(params), flat)
    set_grad(params, 2 * flat)
    assert torch.equal(params[1].grad, 2 * torch.ones(4))


@pytest.mark.parametrize("name", BASELINES)
def test_every_baseline_runs_on_the_engine_and_resumes_identically(tmp_path, name):
    reference = make_engine(tmp_path / "reference", name).run()
    phases = {phase for phase, _ in _calls(tmp_path / "reference", name)}
    assert ("sleep" in phases) == (name in ("reset_distill", "progress_compress"))  # their distillation phase
    plain = make_engine(tmp_path / "plain", "sequential_bc").run()
    assert not all(torch.equal(a, b) for a, b in zip(reference["weights"], plain["weights"], strict=True)), \
        f"{name} trained exactly like sequential fine-tuning"
    out = tmp_path / "killed"

    def kill(k, phase):
        if (k, phase) == (1, "memory"):
            raise KilledError

    with pytest.raises(KilledError):
        make_engine(out, name, after_phase=kill).run()
    resumed = make_engine(out, name, resume=True).run()
    assert all(torch.equal(a, b) for a, b in zip(resumed["weights"], reference["weights"], strict=True))
    assert resumed["evals"] == reference["evals"]


def _calls(out, name):
    engine = make_engine(out.parent / f"calls_{name}", name)
    engine.run()
    return engine.substrate.calls


@pytest.mark.parametrize("name", ["nash_mtl", "pcgrad", "agem"])
def test_gradient_methods_change_the_wake_gradient_only_when_there_is_a_past(tmp_path, name):
    method = METHODS[name](make_engine(tmp_path / "x", name).substrate.method_settings())
    params = _params()
    policy = lambda obs: obs["x"] @ params[0]  # noqa: E731
    memory = OutputDistillationMemory.from_snapshot("a", lambda obs: obs["x"] @ params[0].detach() + 1.0,
                                                    {"x": torch.randn(16, 3)})
    from sr_imitation.stream.methods.base import WakeStep

    method.begin_wake(0, [], None)
    loss = (torch.randn(8, 3) @ params[0]).pow(2).mean() + params[1].pow(2).sum()
    loss.backward()
    before = current_grad(params).clone()
    step = WakeStep(0, 0, params, policy, {}, torch.Generator().manual_seed(0))
    assert method.adjust_gradients(step) == {} and torch.equal(current_grad(params), before)
    method.begin_wake(1, [memory], None)
    past = flat_grad(memory.objective(policy, 16, torch.Generator().manual_seed(5)), params)
    other = torch.randn(past.shape, generator=torch.Generator().manual_seed(9))
    other -= other.dot(past) / past.dot(past) * past
    current = -0.5 * past + other / other.norm() * past.norm()  # conflicts with the past skill (cosine -0.45)
    set_grad(params, current)
    method.adjust_gradients(WakeStep(1, 0, params, policy, {}, torch.Generator().manual_seed(5)))
    after = current_grad(params)
    assert torch.dot(current, past) < 0 and not torch.allclose(after, current)
    assert torch.dot(after, past) >= -1e-5 * past.norm() ** 2  # no longer raises the past skill's loss
    assert torch.dot(after, current) > 0  # and still serves the current skill


def test_reset_distill_resets_the_network_for_every_wake_and_distills_into_the_shared_actor(tmp_path):
    engine = make_engine(tmp_path / "rd", "reset_distill")
    seen = {}
    real_wake = engine.substrate.wake

    def wake(k, memories, weight, method):
        seen[k] = [p.detach().clone() for p in engine.substrate.policy_parameters()]
        return real_wake(k, memories, weight, method)

    engine.substrate.wake = wake
    engine.run()
    for k in range(3):  # every wake starts from the fresh initialization of its stage, not the previous policy
        engine.substrate.reset_networks(k)
        assert all(torch.equal(a, b) for a, b in zip(seen[k], engine.substrate.policy_parameters(), strict=True))
    assert not torch.equal(seen[1][0], seen[2][0])
    # the distilled (final) actor is close to every expert on that expert's states: it is not just the last one
    memories = [engine.substrate.load_memory(k, name="expert") for k in range(3)]
    engine.substrate.load_policy(2, "sleep")
    policy = lambda obs: engine.substrate.gaussian_policy(obs["state"])  # noqa: E731
    with torch.no_grad():
        distilled = [m.loss(policy, dict(m.tensors)).item() for m in memories]
        engine.substrate.load_policy(2, "wake")  # the last expert itself
        expert = [m.loss(policy, dict(m.tensors)).item() for m in memories]
    assert distilled[0] < expert[0] and distilled[1] < expert[1]


def test_progress_and_compress_compresses_the_current_column_under_ewc_of_the_knowledge_base(tmp_path, monkeypatch):
    from sr_imitation.core.sleep import sleep_consolidate as real_sleep

    calls = []

    def recording(params, policy, memories, config, **kwargs):
        reg = kwargs.get("regularizer")
        calls.append({"memories": [m.skill for m in memories], "regularizer": reg,
                      "at_start": None if reg is None else float(reg(params).detach())})
        return real_sleep(params, policy, memories, config, **kwargs)

    monkeypatch.setattr("sr_imitation.stream.substrate.sleep_consolidate", recording)
    engine = make_engine(tmp_path / "pc", "progress_compress")
    engine.run()
    assert [c["memories"] for c in calls] == [["a"], ["b"], ["c"]]  # only the current active column
    assert calls[0]["regularizer"] is None  # nothing to protect before the first compression
    # the knowledge base starts at theta*_{k-1}: F_{k-1}'s term is 0 there, F_0's is not at k = 2
    assert calls[1]["at_start"] == 0.0 and calls[2]["at_start"] > 0.0
    fishers = engine.method.extra_memories(engine.substrate, 3)
    assert [f.skill for f in fishers] == ["a", "b"]  # F_i after compression i; none yet for the last skill
    engine.substrate.load_policy(2, "sleep")
    assert all(f.penalty(engine.substrate.policy_parameters()).item() > 0 for f in fishers)  # it moved, under EWC


def test_a_sleep_regularizer_is_added_to_the_objective_and_its_gradient(tmp_path):
    from sr_imitation.core.sleep import SleepConfig, sleep_consolidate

    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    memory = OutputDistillationMemory.from_snapshot("a", lambda obs: obs["x"] @ torch.ones(3, 2),
                                                    {"x": torch.randn(32, 3)})
    target = [p.detach().clone() for p in net.parameters()]
    config = SleepConfig(max_iterations=200, lr=1e-2, batch_size=8, anchor_strength=0.0, early_stop_tol=0.0)

    def strong(params):
        return 100.0 * sum((p - t).pow(2).sum() for p, t in zip(params, target, strict=True))

    result = sleep_consolidate(list(net.parameters()), lambda obs: net(obs["x"]), [memory], config, progress=False,
                               regularizer=strong)
    moved = sum((p - t).pow(2).sum() for p, t in zip(net.parameters(), target, strict=True)).item()
    assert moved < 1e-2  # held in place by the regularizer
    assert result.sleep_objective[0] >= result.memory_losses[0][0]  # the objective includes R(theta)
    free = torch.nn.Linear(3, 2)
    free.load_state_dict(dict(zip(["weight", "bias"], target, strict=True)))
    sleep_consolidate(list(free.parameters()), lambda obs: free(obs["x"]), [memory], config, progress=False)
    assert sum((p - t).pow(2).sum() for p, t in zip(free.parameters(), target, strict=True)).item() > 10 * moved


def test_componet_starts_with_the_self_bias_and_keeps_earlier_modules_exactly():
    from sr_imitation.substrates.sac.composed_actor import SELF_BIAS, ComposedActor
    from sr_imitation.substrates.sac.config import SACConfig

    torch.manual_seed(0)
    actor = ComposedActor(SACConfig(hidden_dim=16), n_skills=3)
    obs = torch.randn(32, 39)
    actor.train_skill(2)
    w = actor.attention_weights(obs)
    self_weight = torch.exp(torch.tensor(SELF_BIAS)) / (torch.exp(torch.tensor(SELF_BIAS)) + 2)
    assert torch.allclose(w[:, 2], self_weight.expand(32)) and torch.allclose(w[:, 0], w[:, 1])
    trainable = {n for n, p in actor.named_parameters() if p.requires_grad}
    assert trainable == {"heads_mean.2.weight", "heads_mean.2.bias", "heads_log_std.2.weight", "heads_log_std.2.bias",
                         "attention.2.weight", "attention.2.bias"}  # the trunk is frozen after skill 1
    actor.select_skill(0)
    before = [t.detach().clone() for t in actor(obs)]
    actor.train_skill(2)
    opt = torch.optim.SGD([p for p in actor.parameters() if p.requires_grad], lr=0.5)
    for _ in range(5):
        loss = sum(t.pow(2).sum() for t in actor(obs)) + actor.attention_weights(obs)[:, 0].sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    actor.select_skill(0)
    assert all(torch.equal(a, b) for a, b in zip(before, actor(obs), strict=True))  # skill 1 acts as before
    actor.train_skill(0)
    assert {"fc1.weight", "fc2.weight"} <= {n for n, p in actor.named_parameters() if p.requires_grad}


def test_method_options_replace_the_methods_own_settings_and_name_the_valid_ones():
    """--method_options (both substrates): fields of the method's config for this run only; anything else is a
    ValueError naming method_options and the valid names, raised when the method is made (before any file)."""
    from sr_imitation.stream.methods.ewc import EWC, EWCConfig
    from sr_imitation.stream.substrate import MethodSettings

    ewc = METHODS["ewc"](MethodSettings(options={"lam": 100.0}))
    assert ewc.config == EWCConfig(lam=100.0) and EWC.config == EWCConfig()  # the class default is untouched
    assert METHODS["ewc"](MethodSettings()).config.lam == 1.0
    with pytest.raises(ValueError, match=r"method_options: 'ewc' has no option\(s\) \['lambda'\]; its options: "
                                         r"\['lam', 'fisher_states'\]"):
        METHODS["ewc"](MethodSettings(options={"lambda": 100.0}))
    with pytest.raises(ValueError, match="method_options: 'sr' has no option"):
        METHODS["sr"](MethodSettings(options={"lam": 1.0}))


def test_method_options_are_parsed_and_fingerprinted_on_both_substrates():
    from sr_imitation.substrates.act.cli import parse_train_args
    from sr_imitation.substrates.act.trainer import resume_fingerprint
    from sr_imitation.substrates.sac.cli import parse

    act = parse_train_args(["--config_path=configs/needle_cpu.json", "--method=ewc", "--method_options={lam: 100}"])
    assert act.method_options == {"lam": 100.0}
    # a resume with another value is refused (the datasets' digests are given: nothing is recorded here)
    assert resume_fingerprint(act, inputs={}).settings["method_options.lam"] == 100.0
    assert parse(["--config_path=configs/sac_mt5_cpu.json", "--method=ewc", "--method_options={lam: 500}"]
                 ).method_options == {"lam": 500.0}
    with pytest.raises(Exception) as err:  # checked when parsed, for the method the run names (draccus wraps it)
        parse(["--config_path=configs/sac_mt5_cpu.json", "--method_options={lam: 500}"])
    assert "method_options: 'sr' has no option(s) ['lam']" in str(err.value.__cause__)


def test_every_grid_variant_of_the_needle_comparison_sets_existing_options_of_its_method():
    """The comparison's lambda / weight grids (the variants' options) reach their method's config, field by field."""
    from sr_imitation.experiments.needle_compare import VARIANTS
    from sr_imitation.stream.substrate import MethodSettings

    OPTIONS = {variant: spec.options for variant, spec in VARIANTS.items() if spec.options}  # noqa: N806

    assert {"ewc_lam100", "lwf_w0.1", "m2distill_w0.01", "sr_c"} <= set(OPTIONS)
    for variant, options in OPTIONS.items():
        method = METHODS[VARIANTS[variant][0]](MethodSettings(options=options))
        assert {k: getattr(method.config, k) for k in options} == options, variant
