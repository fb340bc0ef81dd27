"""The versions of Python and of the packages hifar depends on (`facade.versions`, and the
`versions` of every evaluation document). Cheap to import: it reads package metadata only."""

from __future__ import annotations

import platform
from importlib import metadata
from typing import Any

# Distribution names of the packages `versions()` reports, by the key it reports them under.
PACKAGES = {
    "jax": "jax", "jaxlib": "jaxlib", "flax": "flax", "brax": "brax", "optax": "optax",
    "mujoco": "mujoco", "mujoco_mjx": "mujoco-mjx", "numpy": "numpy",
    "safetensors": "safetensors",
}


def versions() -> dict:
  """Python and the versions of the packages hifar depends on (None where not installed)."""
  out: dict[str, Any] = {"python": platform.python_version()}
  for key, dist in PACKAGES.items():
    try:
      out[key] = metadata.version(dist)
    except metadata.PackageNotFoundError:
      out[key] = None
  return out
