"""The stream tests' helpers: an engine on the toy substrate (:func:`make_engine`), the exception a test raises to
simulate a killed run (:class:`KilledError`) and :func:`toy_methods`, which lets the methods a comparison restricts to
other substrates run on the toy (import them from here: ``from tests.stream.conftest import make_engine``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sr_imitation.infra.fingerprint import settings_fingerprint
from sr_imitation.stream import RunDirectory, StreamEngine, make_method
from sr_imitation.stream.methods.registry import METHODS
from tests.stream.toy import ToySubstrate

SKILLS = ["a", "b", "c"]


class KilledError(Exception):
    """Raised by a test's ``after_phase`` (or inside a phase) to simulate a killed run."""


def make_engine(out: Path, method: str = "sr", resume: bool = False, settings: dict[str, Any] | None = None,
                after_phase=None, skills: list[str] | None = None, extend_from: Path | None = None,
                substrate_class: type[ToySubstrate] = ToySubstrate, options: dict[str, Any] | None = None,
                **substrate_kwargs: Any) -> StreamEngine:
    """The engine running ``method`` with ``options`` (``--method_options``) on a :class:`ToySubstrate` (or
    ``substrate_class``, a subclass) of ``skills`` in ``out``; the fingerprinted settings are the substrate's
    arguments (``substrate_kwargs`` over their defaults), ``options`` and ``settings``."""
    skills = SKILLS if skills is None else skills
    substrate = substrate_class(out, skills, **substrate_kwargs)
    defaults = {"seed": 0, "sleep": True, "wake_steps": 30, "sleep_iterations": 15, "distill_weight": 0.5,
                "anchor_after_final": False}
    config = {"method": method, "stream": {"skills": skills, "extend_from": None if extend_from is None
                                           else str(extend_from)},
              **({"method_options": dict(options)} if options else {}), **defaults, **substrate_kwargs,
              **(settings or {})}
    run = RunDirectory(out, settings_fingerprint(config), "config.json", config, resume=resume, overwrite=False)
    method_ = make_method(method, substrate, substrate.method_settings(), options)
    return StreamEngine(substrate, method_, run, progress=False, after_phase=after_phase, extend_from=extend_from)


@pytest.fixture
def toy_methods():
    """Methods restricted to other substrates' comparisons (``substrates``) also run on the toy, for this test."""
    saved = {cls: vars(cls).get("substrates") for cls in METHODS.values() if cls.substrates is not None}
    for cls in saved:
        cls.substrates = cls.substrates | {"toy"}
    yield
    for cls, own in saved.items():
        if own is None:  # inherited (PCGrad, Nash-MTL): inherit again
            del cls.substrates
        else:
            cls.substrates = own
