"""sr_imitation.infra.threads: a run warns when its torch threads would share busy cores (measured 5-50x slower)."""

from __future__ import annotations

import logging

import pytest

from sr_imitation.infra import threads
from sr_imitation.infra.threads import oversubscription, warn_if_oversubscribed


@pytest.mark.parametrize(("n_threads", "load", "cores", "warns"), [
    (1, 8.0, 2, False),   # one thread never waits for another
    (2, 0.2, 2, False),   # an idle machine
    (2, 0.5, 2, False),   # half a core of other work: tolerated
    (2, 1.0, 2, True),    # one busy process beside two threads on two cores (the session-30 measurement)
    (4, 10.0, 16, False),  # a large machine with room
    (16, 2.0, 16, True),  # every core asked for while two are busy
])
def test_oversubscription_warns_exactly_when_threads_and_other_work_exceed_the_cores(n_threads, load, cores, warns):
    message = oversubscription(n_threads, load, cores)
    assert (message is not None) == warns
    if warns:
        assert f"torch runs {n_threads} threads on {cores} cores" in message and "torch_threads=1" in message


def test_the_warning_is_logged_from_this_machine_s_load(monkeypatch, caplog):
    monkeypatch.setattr(threads.os, "getloadavg", lambda: (3.0, 3.0, 3.0))
    monkeypatch.setattr(threads.os, "cpu_count", lambda: 2)
    with caplog.at_level(logging.WARNING):
        assert warn_if_oversubscribed(logging.getLogger("t"), 2) is not None
    assert "load is 3.0" in caplog.text
    monkeypatch.setattr(threads.os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    assert warn_if_oversubscribed(logging.getLogger("t"), 2) is None

    def unknown():
        raise OSError("no load average here")

    monkeypatch.setattr(threads.os, "getloadavg", unknown)
    assert warn_if_oversubscribed(logging.getLogger("t"), 2) is None


def test_set_torch_threads_sets_the_number_checks_it_and_keeps_the_default_for_none(monkeypatch):
    import torch

    checked = []
    monkeypatch.setattr(threads, "warn_if_oversubscribed", lambda logger, n: checked.append(n))
    before = torch.get_num_threads()
    try:
        assert threads.set_torch_threads(1, logging.getLogger("t")) == 1 == torch.get_num_threads()
        assert threads.set_torch_threads(None, logging.getLogger("t")) == 1  # None keeps what is in effect
        assert checked == [1, 1]
    finally:
        torch.set_num_threads(before)
