"""Needle-stream metrics: SPI on the tool's own state (scripted expert, still and random policies), the report's
one place that slices the stored agent_pos, and bwt_wake per evaluation seed from the after-wake evaluations."""

from __future__ import annotations

import numpy as np
import pytest

from sr_imitation.core.metrics import bwt_curve, policy_motion, subspace_preservation
from sr_imitation.envs.needle import SKILL_NAMES, NeedleEnv
from sr_imitation.envs.needle.env import STATE_DIM, STATE_NAMES
from sr_imitation.envs.needle.expert import NeedleExpert
from sr_imitation.reporting.results import metric_curves
from sr_imitation.substrates.act.evaluate import NEEDLE_STATE_DIM, SPI_FEATURES, spi_features
from sr_imitation.substrates.act.report import _spi_curves


def _episode(env: NeedleEnv, seed: int, policy: str, max_steps: int) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    expert = NeedleExpert(env, seed=seed) if policy == "expert" else None
    if expert is not None:
        expert.reset()
    rng = np.random.default_rng(seed)
    states = [obs["agent_pos"]]
    for _ in range(max_steps):
        if policy == "expert":
            action = expert.act()
        elif policy == "random":
            action = rng.uniform(-1.0, 1.0, 7)
        else:
            action = np.zeros(7)
        obs, _, terminated, truncated, _ = env.step(action)
        states.append(obs["agent_pos"])
        if terminated or truncated:
            break
    return np.asarray(states, dtype=np.float64)


def test_spi_features_are_the_tools_own_pose_and_jaw():
    assert [STATE_NAMES[i] for i in SPI_FEATURES] == [f"cur_{a}" for a in ("x", "y", "z", "roll", "pitch", "yaw",
                                                                             "jaw")]
    assert NEEDLE_STATE_DIM == STATE_DIM and spi_features(STATE_DIM) == SPI_FEATURES
    assert spi_features(6) == tuple(range(6))  # another env's layout: all entries (with a warning)


@pytest.mark.parametrize("skill", SKILL_NAMES)
def test_spi_expert_near_reference_still_zero_random_below(skill):
    """Measured (4 episodes each): expert vs expert on other reset seeds 0.91-0.995; still policy 0 (the start pose
    the env draws at reset is removed); random 0.37-0.66 (approach 0.66 vs expert 0.91: both move mostly in xyz).
    On the whole 35-d agent_pos the still policy scored 0.38-0.64."""
    env = NeedleEnv(skill=skill, obs_type="agent_pos")

    def motion(policy: str, seeds: range, max_steps: int = 300) -> np.ndarray:
        return policy_motion([_episode(env, s, policy, max_steps) for s in seeds], SPI_FEATURES)

    reference = motion("expert", range(4))
    assert reference.shape[1] == 7
    assert subspace_preservation(reference, reference) == pytest.approx(1.0, abs=1e-12)
    spi_expert = subspace_preservation(reference, motion("expert", range(100, 104)))
    assert spi_expert >= 0.85
    assert subspace_preservation(reference, motion("still", range(100, 104), 50)) <= 0.01
    assert subspace_preservation(reference, motion("random", range(100, 104), 100)) <= spi_expert - 0.15


def _phase(tmp_path, name: str, episodes: dict[str, list[np.ndarray]]):
    d = tmp_path / name
    d.mkdir()
    np.savez(d / "trajectories.npz", **{f"{skill}__{i}": e for skill, eps in episodes.items()
                                        for i, e in enumerate(eps)})
    return d


def test_report_spi_uses_only_the_tool_features(tmp_path):
    """The stored trajectories hold all 35 entries; the report keeps SPI_FEATURES. A skill whose tool keeps
    moving the same way scores 1 whatever the goal entries do; one whose tool stopped scores 0 even though its goal
    entries move (with all 35 entries it would still score high)."""
    rng = np.random.default_rng(0)

    def episode(tool_moves: bool) -> np.ndarray:
        x = np.zeros((40, STATE_DIM))
        if tool_moves:
            x[:, 0:3] = np.cumsum(rng.normal(size=(40, 3)) * [1.0, 0.5, 0.2], axis=0)
        x[:, 7:14] = rng.normal(size=7) * 5.0 + np.linspace(0, 1, 40)[:, None]  # goal: drawn at reset
        return x

    stage_1 = _phase(tmp_path, "s1", {"a": [episode(True) for _ in range(4)]})
    stage_2 = _phase(tmp_path, "s2", {"a": [episode(True) for _ in range(4)], "b": [episode(True) for _ in range(4)]})
    stage_3 = _phase(tmp_path, "s3", {s: [episode(False) for _ in range(4)] for s in ("a", "b", "c")})
    curves, features = _spi_curves([stage_1, stage_2, stage_3], ["a", "b", "c"], n_seeds=2)
    assert features == SPI_FEATURES
    assert curves.shape == (2, 3) and np.isnan(curves[:, 0]).all()
    np.testing.assert_array_less(0.8, curves[:, 1])
    np.testing.assert_array_equal(curves[:, 2], 0.0)


def test_report_bwt_wake_per_evaluation_seed():
    nan = float("nan")
    s_final = np.array([[[1.0, nan], [0.5, 0.4]], [[0.8, nan], [0.6, 0.2]]])  # [seed, k, i]
    s_wake = np.array([[[0.7, nan], [0.9, 0.3]], [[0.6, nan], [0.5, 0.1]]])
    curves = metric_curves(s_final, ["a", "b"], [], np.stack([np.diag(w) for w in s_wake]))
    np.testing.assert_allclose(curves["bwt"][:, 1], [0.5 - 1.0, 0.6 - 0.8])
    np.testing.assert_allclose(curves["bwt_wake"][:, 1], [0.5 - 0.7, 0.6 - 0.6])
    np.testing.assert_allclose(curves["bwt_wake"][0], bwt_curve(s_final[0], [0.7, 0.3]), equal_nan=True)
    assert "bwt_wake" not in metric_curves(s_final, ["a", "b"], [], None)
