"""The tiny ACT datasets, environment and stream config of the ACT substrate's tests, for tests outside its folder."""

from __future__ import annotations

from tests.substrates.act.helpers import fake_env_factory, make_skill_dataset, tiny_stream_config

__all__ = ["fake_env_factory", "make_skill_dataset", "tiny_stream_config"]
