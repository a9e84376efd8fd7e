"""Benchmarks of the SAC substrate (docs/BENCHMARKS.md): ``python -m sr_imitation.benchmarks.sac``.

* SAC updates/s: our update (excitable actor, observation normalizer, Eq. 3 after every update) against a plain
  CleanRL-style SAC update of the same sizes (ReLU actor, no normalizer), and their ratio;
* environment steps/s of one Meta-World skill, with random actions and with the actor in the loop;
* one sleep iteration over k critic memories (k gradients, Gram matrix, Nash / Frank-Wolfe, Adam, excitability)
  against k plain forward+backward passes of the memory objectives;
* the evaluation-harness check: Meta-World's scripted policies and a random policy through our evaluator.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch

from sr_imitation.core.excitability import ExcitabilityConfig, update_excitability
from sr_imitation.core.sleep import SleepConfig, sleep_consolidate
from sr_imitation.envs.metaworld.tasks import ACT_DIM, MT5_STREAM, OBS_DIM, SkillEnv, scripted_policy
from sr_imitation.substrates.sac.config import SACConfig
from sr_imitation.substrates.sac.critic_memory import CriticMemory
from sr_imitation.substrates.sac.evaluate import evaluate_policy, random_policy
from sr_imitation.substrates.sac.sac import ReplayBuffer, SACAgent


def replay_buffer(n: int = 20_000) -> ReplayBuffer:
    """``n`` random MT5-shaped transitions (seeded)."""
    rng = np.random.default_rng(0)
    rb = ReplayBuffer(n)
    for _ in range(n):
        rb.add(rng.normal(size=OBS_DIM), rng.uniform(-1, 1, ACT_DIM), rng.uniform(0, 10), rng.normal(size=OBS_DIM),
               False)
    return rb


def bench_updates(batch_size: int, hidden: int, iters: int, repeats: int = 3) -> dict[str, float]:
    rb = replay_buffer()
    rng = np.random.default_rng(0)
    cfg = SACConfig(batch_size=batch_size, hidden_dim=hidden)
    plain_cfg = dataclasses.replace(cfg, normalize_observations=False)
    out = {}
    agents = {"plain": SACAgent(plain_cfg, plain_actor=True), "ours": SACAgent(cfg, ExcitabilityConfig())}
    agents["ours"].normalizer.update(rb.obs[:1000])
    best = {name: float("inf") for name in agents}
    for _ in range(repeats):  # interleaved, best of repeats: robust to other load on shared cores
        for name, agent in agents.items():
            rate = 1e-3 if name == "ours" else 0.0
            for _ in range(5):
                agent.update(rb.batch(rb.indices(batch_size, rng)), rate)
            t = time.perf_counter()
            for _ in range(iters):
                agent.update(rb.batch(rb.indices(batch_size, rng)), rate)
            best[name] = min(best[name], (time.perf_counter() - t) / iters)
    for name, sec in best.items():
        out[f"{name}_ms"] = sec * 1e3
        out[f"{name}_updates_per_s"] = 1.0 / sec
    out["ratio_ours_over_plain_time"] = best["ours"] / best["plain"]
    return out


def bench_env(steps: int) -> dict[str, float]:
    out = {}
    with SkillEnv("door-open-v3", seed=0) as env:
        agent = SACAgent(SACConfig(), ExcitabilityConfig())
        agent.normalizer.update(np.zeros((2, OBS_DIM)))
        for name, act in (("random", random_policy(0)), ("actor", lambda o: agent.act(o))):
            obs = env.reset()
            t = time.perf_counter()
            for _ in range(steps):
                step = env.step(act(obs))
                obs = env.reset() if step.truncated else step.obs
            out[f"{name}_steps_per_s"] = steps / (time.perf_counter() - t)
    return out


def critic_memories(agent: SACAgent, k: int, states: int = 1000) -> list[CriticMemory]:
    """``k`` distinct critic memories of ``agent`` (its critic nudged by 0.01 x noise before each; seeded states)."""
    memories = []
    for i in range(k):
        with torch.no_grad():
            for p in agent.critic.parameters():
                p.add_(0.01 * torch.randn_like(p))
        memories.append(CriticMemory.from_agent(f"skill{i}", agent,
                                                np.random.default_rng(i).normal(size=(states, OBS_DIM))))
    return memories


def bench_sleep(k: int, iters: int, batch_size: int = 64) -> dict[str, float]:
    torch.manual_seed(0)
    agent = SACAgent(SACConfig(), ExcitabilityConfig())
    agent.normalizer.update(np.random.default_rng(0).normal(size=(100, OBS_DIM)))
    memories = critic_memories(agent, k)
    params = agent.actor_parameters()
    gen = torch.Generator().manual_seed(0)
    # k plain forward+backward passes of the memory objectives
    for _ in range(3):
        for m in memories:
            m.objective(agent.policy_fn, batch_size, gen).backward()
    t = time.perf_counter()
    for _ in range(iters):
        for m in memories:
            agent.actor.zero_grad(set_to_none=True)
            m.objective(agent.policy_fn, batch_size, gen).backward()
    plain = (time.perf_counter() - t) / iters

    def exc_step(_it: int) -> None:
        states = torch.cat([m.sample(batch_size, gen)["state"] for m in memories])
        with torch.no_grad():
            agent.policy_fn(states)
        update_excitability(agent.actor, 1e-2)

    cfg = SleepConfig.mt5(max_iterations=iters, early_stop_tol=0.0, anchor_tau=None, batch_size=batch_size)
    anchor = [p.detach().clone() for p in params]
    t = time.perf_counter()
    result = sleep_consolidate(params, agent.policy_fn, memories, cfg, anchor_params=anchor,
                               step_callback=exc_step, progress=False)
    sleep = (time.perf_counter() - t) / result.stop_iteration
    return {"k": k, "sleep_iteration_ms": sleep * 1e3, "k_fwd_bwd_ms": plain * 1e3, "ratio": sleep / plain}


def bench_scripted(episodes: int) -> list[dict[str, float | str]]:
    rows = []
    for skill in MT5_STREAM:
        with SkillEnv(skill, seed=0) as env:
            sweep = evaluate_policy(scripted_policy(skill), env, 50, seed=0, configurations=range(50))
            uniform = evaluate_policy(scripted_policy(skill), env, episodes, seed=1)
            rand = evaluate_policy(random_policy(1), env, episodes, seed=1)
        rows.append({"skill": skill, "scripted_50_configs": sweep.success_rate,
                     f"scripted_{episodes}_uniform": uniform.success_rate,
                     f"random_{episodes}_uniform": rand.success_rate})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--what", nargs="+", default=["updates", "env", "sleep", "scripted"],
                        choices=["updates", "env", "sleep", "scripted"])
    parser.add_argument("--update-iters", type=int, default=100)
    parser.add_argument("--env-steps", type=int, default=3000)
    parser.add_argument("--sleep-iters", type=int, default=30)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"threads {torch.get_num_threads()}")
    if "updates" in args.what:
        for bs, hidden in ((256, 256), (128, 256)):
            r = bench_updates(bs, hidden, args.update_iters)
            print(f"SAC update batch {bs} hidden {hidden}: plain {r['plain_ms']:.2f} ms "
                  f"({r['plain_updates_per_s']:.1f}/s), ours {r['ours_ms']:.2f} ms ({r['ours_updates_per_s']:.1f}/s), "
                  f"ratio ours/plain {r['ratio_ours_over_plain_time']:.3f}")
    if "env" in args.what:
        r = bench_env(args.env_steps)
        print(f"env door-open-v3: random actions {r['random_steps_per_s']:.0f} steps/s, "
              f"actor in the loop {r['actor_steps_per_s']:.0f} steps/s")
    if "sleep" in args.what:
        for k in (2, 5):
            r = bench_sleep(k, args.sleep_iters)
            print(f"sleep k={k}: one iteration {r['sleep_iteration_ms']:.2f} ms vs {k} fwd+bwd "
                  f"{r['k_fwd_bwd_ms']:.2f} ms, ratio {r['ratio']:.2f}")
    if "scripted" in args.what:
        for row in bench_scripted(args.episodes):
            print("harness " + ", ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}"
                                         for k, v in row.items()))


if __name__ == "__main__":
    main()
