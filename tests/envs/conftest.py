"""Keep tests offline and their caches out of $HOME (integration notes §4); EGL rendering on CPU."""

import os
import tempfile

from sr_imitation.offscreen import setup_offscreen_rendering

setup_offscreen_rendering()
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
_cache = tempfile.mkdtemp(prefix="sr_needle_test_cache_")
os.environ.setdefault("HF_HOME", os.path.join(_cache, "hf"))
os.environ.setdefault("HF_DATASETS_CACHE", os.path.join(os.environ["HF_HOME"], "datasets"))
os.environ.setdefault("MESA_SHADER_CACHE_DIR", os.path.join(_cache, "mesa"))
