"""Shared checks that a substrate's stream gives the sleep of stage k the right checkpoints (Eq. 2 and the anchor).

At stage k >= 2 (1-based) the gate of Eq. 2 needs theta_i^wake for i < k only (passing theta_k^wake too would make
c_k = 0 at the start of sleep and keep the gate always on), and the anchor pulls toward theta_{k-1}^sleep
(theta_1^wake for k = 2). :func:`sleep_recorder` wraps the engine's ``sleep_consolidate`` to record each call;
:func:`assert_sleep_wiring` compares the records with the parameters seen at the end of every wake and sleep.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import torch

from sr_imitation.stream import substrate as substrate_module


def clone(tensors) -> list[torch.Tensor]:
    return [t.detach().clone() for t in tensors]


def same(a, b) -> bool:
    return len(a) == len(b) and all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b, strict=True))


def sleep_recorder(sleeps: list[dict[str, Any]],
                   measure: Callable[[Any, Any], dict[str, Any]] | None = None) -> Callable[..., Any]:
    """A stand-in for ``sleep_consolidate`` that appends each call's inputs and outputs to ``sleeps``; ``measure``
    (policy, memories) -> values is recorded before (``<key>_before``) and after (``<key>_after``) the sleep."""
    real = substrate_module.sleep_consolidate

    def recording_sleep(params, policy, memories, config, anchor_params=None, wake_snapshots=(), **kwargs):
        params = list(params)
        call = {"start": clone(params), "anchor": None if anchor_params is None else clone(anchor_params),
                "wake_snapshots": [clone(s) for s in wake_snapshots], "skills": [m.skill for m in memories],
                "kwargs": kwargs}
        if measure is not None:
            call.update({f"{key}_before": v for key, v in measure(policy, memories).items()})
        result = real(params, policy, memories, config, anchor_params=anchor_params, wake_snapshots=wake_snapshots,
                      **kwargs)
        call.update(end=clone(params), result=result)
        if measure is not None:
            call.update({f"{key}_after": v for key, v in measure(policy, memories).items()})
        sleeps.append(call)
        return result

    return recording_sleep


def assert_sleep_wiring(wakes: list[list[torch.Tensor]], sleeps: list[dict[str, Any]], skills: list[str]) -> None:
    """Stages 2..K each slept once, on M_1..M_k, from theta_k^wake, with gates from theta_i^wake (i < k) whose
    distances are the recorded c_i, anchored to what stage k-1 ended with, final-skill flag on the last stage only."""
    n = len(skills)
    assert len(wakes) == n and len(sleeps) == n - 1
    for k, call in zip(range(2, n + 1), sleeps, strict=True):
        assert call["skills"] == skills[:k]
        # The sleep starts at theta_k^wake ...
        assert same(call["start"], wakes[k - 1])
        # ... the gate sees theta_i^wake for i < k: exactly k - 1 of them, those of skills 1..k-1 ...
        assert len(call["wake_snapshots"]) == k - 1
        for i, snapshot in enumerate(call["wake_snapshots"], start=1):
            assert same(snapshot, wakes[i - 1]), (k, i)
        # ... so no c_i is 0 at the start of sleep (c_k would be), and the recorded c_i are those distances.
        distances = call["result"].anchor_distances
        assert len(distances) == k - 1 and min(distances) > 0
        for c, snapshot in zip(distances, call["wake_snapshots"], strict=True):
            expected = torch.sqrt(sum(((a - b) ** 2).sum() for a, b in zip(call["start"], snapshot, strict=True)))
            assert c == pytest.approx(float(expected), rel=1e-5)
        # The anchor is theta_{k-1}^sleep (theta_1^wake for k = 2): what the previous stage ended with.
        previous_end = wakes[0] if k == 2 else sleeps[k - 3]["end"]
        assert same(call["anchor"], previous_end)
        assert not same(call["anchor"], call["start"])
        assert call["kwargs"]["is_final_skill"] is (k == n)
