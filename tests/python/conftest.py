"""Shared pytest setup: JAX on CPU with a persistent compilation cache owned by the tests."""

import gc
import os
from pathlib import Path

import pytest

_CACHE = Path(__file__).resolve().parents[1] / ".cache" / "jax"
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
_CACHE.mkdir(parents=True, exist_ok=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
  """Frees a test file's compiled XLA executables once the file is done.

  XLA's CPU backend maps every compiled executable's code into memory regions of its own, and
  the kernel caps the regions a process may map (vm.max_map_count, 65530 by default). A test
  file adds up to 19,500 of them (test_learner_train.py); the whole suite in one pytest process
  ran past the cap, the next compile failed ("LLVM compilation error: Cannot allocate memory")
  and pytest aborted while it wrote that executable to the persistent cache. A later file that
  needs an executable again reads it from the persistent cache.
  """
  yield
  import jax  # not at the top: JAX reads the environment set above when it is imported

  jax.clear_caches()
  gc.collect()
