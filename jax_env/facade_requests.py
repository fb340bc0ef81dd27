"""The requests the Rust CLI sends through the facade, typed, and their one checker.

Every facade request is a dict of known keys (docs/contracts.md, "The facade"). Each has a
frozen dataclass here, and the CLI a serde struct of the same fields
(`hifar-cli/src/commands/facade.rs`); `parse` is the one place that turns a request dict into
its dataclass. A key the dataclass does not have is an error rather than a silently ignored
setting (the error lists the valid keys, the dataclass's fields in order), a field without a
default must have a value, and a key sent as None takes the field's default. The value checks
that need a module's vocabulary stay with that module. Errors are one-line `ValueError`s that
start with the facade function's name.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence, TypeVar

from jax_env.physics import BACKENDS

R = TypeVar("R")

# kw_only: the fields keep the order of the contract, with and without defaults mixed.
_request = dataclasses.dataclass(frozen=True, kw_only=True)


@_request
class TrainRequest:
  """`facade.train_stage`: one stage of a run."""
  stage: dict
  stage_name: str | None = None
  stage_dir: str
  seed: int
  backend: str
  num_envs: int | None = None
  init_checkpoint: str | None = None
  resume_checkpoint: str | None = None
  log_file: str | None = None


@_request
class EvaluateRequest:
  """`facade.evaluate`: one evaluation protocol on a checkpoint."""
  checkpoint: str
  stage: dict | None = None
  protocol: str
  trials: int | None = None
  backend: str
  actor: str | None = None  # None: the deployable actor (evaluation.policy.ACTORS)
  seed: int = 0
  out_dir: str
  batch_size: int | None = None


@_request
class RolloutRequest:
  """`facade.rollout`: one recorded episode."""
  checkpoint: str
  stage: dict | None = None
  scenario: str = "supine"
  terrain: str = "flat"
  push_force: float = 0.0
  push_direction: str | None = None
  seed: int = 0
  backend: str = "native"
  duration_s: float | None = None
  video: str | None = None
  filmstrip: str | None = None


@_request
class ReportRequest:
  """`facade.report`: plots and report.md of a run."""
  run: str
  out_dir: str | None = None


@_request
class ExportRequest:
  """`facade.export_onnx`: the deployable actor as ONNX."""
  checkpoint: str
  out: str
  tolerance: float | None = None
  stage: dict | None = None


@_request
class ActRequest:
  """`facade.act`: deterministic actions for observation rows."""
  checkpoint: str
  obs: list
  history: list | None = None


REQUESTS = {"train_stage": TrainRequest, "evaluate": EvaluateRequest,
            "rollout": RolloutRequest, "report": ReportRequest, "export_onnx": ExportRequest,
            "act": ActRequest}


def fields(cls: type) -> tuple[str, ...]:
  """The request keys of a request dataclass, in order."""
  return tuple(f.name for f in dataclasses.fields(cls))


def parse(what: str, cls: type[R], request: Mapping[str, Any]) -> R:
  """The request dict as its dataclass `cls`, checked as the module docstring says."""
  if not isinstance(request, Mapping):
    raise ValueError(f"{what}: the request must be a dict, got {type(request).__name__}")
  required = tuple(f.name for f in dataclasses.fields(cls)
                   if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING)
  check_keys(what, request, fields(cls), required)
  return cls(**{k: v for k, v in request.items() if v is not None})


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
