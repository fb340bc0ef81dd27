"""Checks of the requests the Rust CLI sends through the facade, with one wording for all.

Every facade request is a dict of known keys (docs/contracts.md, "The facade"); a key the
function does not know is an error rather than a silently ignored setting, and the error lists
the valid keys. Errors are one-line `ValueError`s that start with the facade function's name.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from jax_env.physics import BACKENDS


def check_keys(what: str, request: Mapping[str, Any], keys: Sequence[str],
               required: Sequence[str] = ()) -> None:
  """`request` holds only `keys`, and a value (not None or "") for each of `required`."""
  unknown = sorted(set(request) - set(keys))
  if unknown:
    raise ValueError(f"{what}: unknown request key(s) {', '.join(unknown)}; valid: "
                     f"{', '.join(keys)}")
  for key in required:
    if request.get(key) is None or request.get(key) == "":
      raise ValueError(f"{what}: request key {key!r} is required")


def check_choice(what: str, noun: str, value: Any, valid: Sequence[str]) -> str:
  """`value`, which must be one of `valid`."""
  if value not in valid:
    raise ValueError(f"{what}: unknown {noun} {value!r}; valid: {', '.join(valid)}")
  return value


def check_backend(what: str, backend: Any) -> str:
  """A physics backend name ("auto" is resolved by the CLI before a request is sent)."""
  return check_choice(what, "backend", backend, BACKENDS)
