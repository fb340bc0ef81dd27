"""The one request checker (jax_env/facade_requests.py): a request dict becomes its dataclass."""

import pytest

from jax_env import facade_requests as r


def test_a_request_becomes_its_dataclass_with_defaults_for_none():
  req = r.parse("rollout", r.RolloutRequest,
                {"checkpoint": "c", "scenario": None, "push_force": 20.0, "seed": None})
  assert (req.checkpoint, req.scenario, req.push_force, req.seed) == ("c", "supine", 20.0, 0)
  assert req.push_direction is None and req.backend == "native"


def test_unknown_keys_list_the_fields_in_order_and_required_ones_must_have_values():
  with pytest.raises(ValueError, match=r"^report: unknown request key\(s\) bogus, x; valid: "
                     r"run, out_dir$"):
    r.parse("report", r.ReportRequest, {"run": "r", "x": 1, "bogus": 2})
  for missing in ({}, {"run": None}, {"run": ""}):
    with pytest.raises(ValueError, match=r"^report: request key 'run' is required$"):
      r.parse("report", r.ReportRequest, missing)
  with pytest.raises(ValueError, match="the request must be a dict"):
    r.parse("act", r.ActRequest, ["c", []])


def test_every_facade_request_has_a_dataclass():
  assert r.fields(r.TrainRequest) == ("stage", "stage_name", "stage_dir", "seed", "backend",
                                      "num_envs", "init_checkpoint", "resume_checkpoint",
                                      "log_file")
  assert set(r.REQUESTS) == {"train_stage", "evaluate", "rollout", "report", "export_onnx",
                             "act"}
