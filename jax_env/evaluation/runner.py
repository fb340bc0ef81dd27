"""Runs an evaluation protocol on a checkpoint: eval.json, eval.csv and eval.md
(docs/contracts.md, "facade.evaluate").

Every trial is one episode of the checkpoint's deployable actor in the nominal environment
(conditions.evaluation_stage) under its cell's condition. All trials of all cells form one list
that is cut into batches of a fixed size (the last padded with repeats whose results are
dropped), and one compiled rollout runs every batch: cells differ only in data (scenario and
terrain indices, physical parameters, push schedule), so the protocol compiles once. Trial t of
cell c uses key t of split(fold_in(seed_key(seed), c), trials), so a result does not depend on
the batch size or on the other cells.

Success, recovery time and how the episode ended are the env's own `episode_metrics` of each
env's first episode: the rollout runs exactly `episode_steps` control steps, so every first
episode ends at the last step, or earlier by a numerical blow-up. As in the paper's evaluation
(Webots, no early end), the stage's termination rules do not end a trial: they are training
devices (no value bootstrap for a dive or a roll onto a side), and one that holds for a moment
of a roll that then stands up would count a recovery as a failure. The env records instead the
first rule that held before the trial succeeded (`rule_met`), and each cell reports beside its
successes how many remain within the stage's rules (those no rule would have ended) and how
many trials each rule would have ended: the stricter reading, as `hifar eval` measured before.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jax_env import facade_requests
from jax_env import versions as versions_lib
from jax_env.evaluation import conditions as cond_lib
from jax_env.evaluation import policy as policy_lib
from jax_env.evaluation import protocols as proto_lib
from jax_env.evaluation import stats
from jax_env.files import write_atomic
from jax_env.learner import train as train_lib
from jax_env.stage_config import EPISODE_ENDS, TERMINATION_RULES

# 2 (2026-12-07): the stage's termination rules no longer end a trial; `failures` counts only
# `TRIAL_ENDS`, and `within_rules` keeps the stricter reading that version 1 reported.
FORMAT_VERSION = 2
FILES = ("eval.json", "eval.csv", "eval.md")
DEFAULT_BATCH = {"mjx": 1024, "native": 128}
# How a trial can end when the stage's rules do not end it.
TRIAL_ENDS = tuple(end for end in EPISODE_ENDS if end not in TERMINATION_RULES)
CSV_FIELDS = ("experiment", "scenario", "setting", "value", "trials", "successes",
              "success_rate", "ci_low", "ci_high", "recovery_time_mean", "recovery_time_std",
              "paper_success_rate", "paper_recovery_time_mean", "paper_recovery_time_std"
              ) + tuple(f"failed_{end}" for end in TRIAL_ENDS) + (
              "within_rules_successes",) + tuple(f"rule_met_{r}" for r in TERMINATION_RULES)
EXPERIMENT_TITLES = {
    "standard": "Standard supine and prone recovery",
    "planar_push": "Planar push (forward from prone, backward from supine; 0.8 s after the "
                   "recovery starts, 200 ms)",
    "lateral_push": "Lateral push (leftward; 0.8 s after the recovery starts, 200 ms)",
    "load": "Extra torso mass",
    "friction": "Floor friction coefficient",
    "torque_limit": "Torque limit (fraction of the stage's actuator limits)",
    "random_initial": "Random initial states",
    "terrain": "Terrain",
    "keystate": "Start states of the key-state curriculum (nominal conditions)",
}

# Compiled rollouts by (checkpoint, its mtime, stage, backend, batch): a second evaluation of the
# same policy in the same process (tests, a report that evaluates twice) does not recompile.
_ROLLOUTS: dict = {}


def _validate(request: dict) -> dict:
  req = facade_requests.parse("evaluate", facade_requests.EvaluateRequest, request)
  protocol = facade_requests.check_choice("evaluate", "protocol", req.protocol,
                                          tuple(proto_lib.PROTOCOLS))
  backend = facade_requests.check_backend("evaluate", req.backend)
  actor = (policy_lib.DEPLOYABLE if req.actor is None else
           facade_requests.check_choice("evaluate", "actor", req.actor, policy_lib.ACTORS))
  trials = proto_lib.DEFAULT_TRIALS[protocol] if req.trials is None else int(req.trials)
  if trials < 1:
    raise ValueError(f"evaluate: trials {trials} must be >= 1")
  batch = req.batch_size
  if batch is not None and int(batch) < 1:
    raise ValueError(f"evaluate: batch_size {batch} must be >= 1")
  seed = int(req.seed)
  if not 0 <= seed < 2**64:
    raise ValueError(f"evaluate: seed {seed} is not a u64")
  return dict(checkpoint=Path(req.checkpoint), stage=req.stage, protocol=protocol,
              trials=trials, backend=backend, actor=actor, seed=seed, out_dir=Path(req.out_dir),
              batch_size=None if batch is None else int(batch))


def trial_keys(seed: int, cell_index: int, trials: int) -> np.ndarray:
  """Keys [trials, 2] of one cell's trials."""
  return np.asarray(jax.random.split(jax.random.fold_in(train_lib.seed_key(seed), cell_index), trials))


def make_rollout(env, policy: policy_lib.Policy,
                 actor: str = policy_lib.DEPLOYABLE) -> Callable:
  """(keys [B], ConditionArrays [B]) -> (success [B], recovery_time [B], end [B] and rule_met
  [B] (indices into EPISODE_ENDS), ended [B]) of the first episode of each env, over exactly
  env.episode_steps control steps (pure; jit it)."""
  act_step = policy_lib.episode_step(policy, env, actor)

  def rollout(keys, arrays):
    batch = keys.shape[0]
    state = cond_lib.start_arrays(env, keys, arrays)
    history = policy.initial_history(batch)

    def body(carry, _):
      state, history, ended, record = carry
      state, history = act_step((state, history))
      first = (state.done > 0) & ~ended
      record = {k: jnp.where(first, state.episode_metrics[k], v) for k, v in record.items()}
      return (state, history, ended | first, record), None

    record = {"success": jnp.zeros((batch,)), "recovery_time": jnp.full((batch,), jnp.nan),
              "end": jnp.zeros((batch,)), "rule_met": jnp.zeros((batch,))}
    init = (state, history, jnp.zeros((batch,), bool), record)
    (_, _, ended, record), _ = jax.lax.scan(body, init, None, length=env.episode_steps)
    return (record["success"], record["recovery_time"], record["end"], record["rule_met"],
            ended)

  return rollout


def _compiled(policy: policy_lib.Policy, stage: dict, backend: str, batch: int, actor: str):
  from jax_env.env import FallRecoveryEnv

  checkpoint = policy.directory
  params = checkpoint / "params.safetensors"
  stamp = params.stat().st_mtime_ns if params.exists() else None
  key = (str(checkpoint.resolve()), stamp, json.dumps(stage, sort_keys=True), backend, batch,
         actor)
  if key not in _ROLLOUTS:
    env = FallRecoveryEnv(cond_lib.evaluation_stage(stage), backend=backend,
                          rules_end_episodes=False)
    policy_lib.check_features(policy, env)
    _ROLLOUTS.clear()  # one policy at a time: compiled rollouts hold their constants
    _ROLLOUTS[key] = (policy, env, jax.jit(make_rollout(env, policy, actor)))
  return _ROLLOUTS[key]


def evaluate(request: dict, callback: Callable[[dict], str] | None = None) -> dict:
  """Runs the protocol; see docs/contracts.md for the request, progress and result keys."""
  r = _validate(request)
  loaded = policy_lib.load(r["checkpoint"], r["actor"])
  stage = policy_lib.stage_of(loaded, r["stage"])
  cells = proto_lib.cells(r["protocol"])
  trials = r["trials"]
  total = len(cells) * trials
  batch = min(r["batch_size"] or DEFAULT_BATCH[r["backend"]], total)
  policy, env, rollout = _compiled(loaded, stage, r["backend"], batch, r["actor"])

  # The flat trial list: (cell index, key), with the conditions as rows of data.
  cell_of = np.repeat(np.arange(len(cells)), trials)
  keys = np.concatenate([trial_keys(r["seed"], c, trials) for c in range(len(cells))])
  rows = cond_lib.condition_arrays(env, [cells[c].condition for c in cell_of])
  rows = jax.tree_util.tree_map(np.asarray, rows)
  success = np.zeros(total, np.float32)
  recovery = np.full(total, np.nan, np.float32)
  end = np.zeros(total, np.int32)
  rule_met = np.zeros(total, np.int32)

  for lo in range(0, total, batch):
    idx = np.minimum(np.arange(lo, lo + batch), total - 1)  # pad with the last trial
    arrays = jax.tree_util.tree_map(lambda x: jnp.asarray(x[idx]), rows)
    s, t, e, m, ended = jax.device_get(rollout(jnp.asarray(keys[idx]), arrays))
    if not np.all(ended):
      raise RuntimeError("evaluate: an episode did not end after episode_steps control steps")
    n = min(batch, total - lo)
    success[lo:lo + n], recovery[lo:lo + n] = s[:n], t[:n]
    end[lo:lo + n], rule_met[lo:lo + n] = e[:n], m[:n]
    done = lo + n
    if callback is not None:
      answer = callback({"cells_done": done // trials, "cells_total": len(cells),
                         "trials_done": done, "trials_total": total,
                         "cell": cells[cell_of[done - 1]].label})
      if answer == "interrupt":
        return {"status": "interrupted", "files": [], "markdown": ""}
      if answer not in (None, "continue"):
        raise ValueError(f"evaluate: callback answered {answer!r}; valid: continue, interrupt")

  per_cell = lambda a, c: a[c * trials:(c + 1) * trials]
  results = [_cell_result(cell, per_cell(success, c), per_cell(recovery, c), per_cell(end, c),
                          per_cell(rule_met, c)) for c, cell in enumerate(cells)]
  doc = _document(r, policy, env, results)
  markdown = render_markdown(doc)
  files = _write(r["out_dir"], {
      "eval.json": json.dumps(doc, indent=2) + "\n",
      "eval.csv": render_csv(results),
      "eval.md": markdown,
  })
  return {"status": "completed", "files": files, "markdown": markdown}


def _cell_result(cell: proto_lib.Cell, success: np.ndarray, recovery: np.ndarray,
                 end: np.ndarray, rule_met: np.ndarray) -> dict:
  ok = success > 0.5
  n, k = int(success.shape[0]), int(ok.sum())
  within = int(np.sum(ok & (rule_met == 0)))
  low, high = stats.wilson_interval(k, n)
  mean, std = stats.mean_std([float(x) for x in recovery[ok]])
  return {
      "experiment": cell.experiment, "scenario": cell.scenario, "setting": cell.setting,
      "value": cell.value, "trials": n, "successes": k, "success_rate": k / n,
      "ci95": [low, high], "recovery_time_mean": mean, "recovery_time_std": std,
      "paper_success_rate": cell.paper_success_rate,
      "paper_recovery_time": (None if cell.paper_recovery_time is None
                              else list(cell.paper_recovery_time)),
      "failures": {name: int(np.sum(~ok & (end == EPISODE_ENDS.index(name))))
                   for name in TRIAL_ENDS},
      "within_rules": {"successes": within, "success_rate": within / n,
                       "rule_met": {name: int(np.sum(rule_met == EPISODE_ENDS.index(name)))
                                    for name in TERMINATION_RULES}},
      "condition": cell.condition.to_dict(),
  }


def _document(r: dict, policy: policy_lib.Policy, env, results: list[dict]) -> dict:
  setup = cond_lib.nominal_setup(env)
  setup.update(push_start_s=proto_lib.PUSH_START_S, push_duration_s=proto_lib.PUSH_DURATION_S)
  return {
      "format_version": FORMAT_VERSION, "protocol": r["protocol"], "backend": r["backend"],
      "actor": r["actor"], "seed": r["seed"], "trials": r["trials"], "checkpoint": str(r["checkpoint"].resolve()),
      "stage": policy.meta.get("stage"), "env_steps": policy.meta.get("env_steps"),
      "versions": versions_lib.versions(), "conditions": setup, "cells": results,
  }


def render_csv(results: list[dict]) -> str:
  out = io.StringIO()
  w = csv.DictWriter(out, fieldnames=CSV_FIELDS, lineterminator="\n")
  w.writeheader()
  for c in results:
    paper_t = c["paper_recovery_time"] or [None, None]
    row = {k: c.get(k) for k in CSV_FIELDS}
    row.update(ci_low=c["ci95"][0], ci_high=c["ci95"][1], paper_recovery_time_mean=paper_t[0],
               paper_recovery_time_std=paper_t[1])
    row.update({f"failed_{end}": n for end, n in c["failures"].items()})
    row.update(within_rules_successes=c["within_rules"]["successes"])
    row.update({f"rule_met_{r}": n for r, n in c["within_rules"]["rule_met"].items()})
    w.writerow({k: "" if v is None else v for k, v in row.items()})
  return out.getvalue()


def _actor(actor: str) -> str:
  if actor == policy_lib.PRIVILEGED:
    return ("the privileged actor (the base policy with the encoder's latent from the "
            "simulator's state; not deployable)")
  return "the deployable actor (adaptation module + base policy)"


def _pct(x: float | None) -> str:
  return "—" if x is None else f"{100 * x:.0f}%"


def _entry(c: dict) -> str:
  low, high = c["ci95"]
  return (f"{_pct(c['success_rate'])} [{100 * low:.0f}–{100 * high:.0f}] · "
          f"{_pct(c['paper_success_rate'])}")


def _time(mean, std) -> str:
  return "—" if mean is None else f"{mean:.3f} ± {std:.3f}"


def _failures(counts: dict[str, int]) -> str:
  """Trials counted by how their episode ended or which rule held: "2 at the time limit, 6
  upside down face down"."""
  words = {"time_limit": "at the time limit", "blow_up": "numerical blow-up"}
  parts = [f"{n} {words.get(end, end.replace('_', ' '))}" for end, n in counts.items() if n]
  return ", ".join(parts) or "—"


def _within_rules(c: dict) -> str:
  """A cell under the stage's termination rules: "5/16 (11 upside down face down)"."""
  w = c["within_rules"]
  met = _failures(w["rule_met"])
  return f"{w['successes']}/{c['trials']}" + ("" if met == "—" else f" ({met})")


def _sum_over(cells: list[dict], counts) -> dict[str, int]:
  names = counts(cells[0])
  return {k: sum(counts(c)[k] for c in cells) for k in names}


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
  lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
  return lines + ["| " + " | ".join(row) + " |" for row in rows]


def render_markdown(doc: dict) -> str:
  """eval.md: one table per experiment laid out like the paper's (rows prone / supine, columns
  the settings), each entry "ours [95 % Wilson CI] · paper"."""
  setup = doc["conditions"]
  lines = [
      f"# Evaluation: {doc['protocol']} protocol, {doc['backend']} backend", "",
      f"- checkpoint: `{doc['checkpoint']}` (stage `{doc['stage']}`, {doc['env_steps']} env "
      "steps)",
      f"- {doc['trials']} trials per cell, seed {doc['seed']}, {_actor(doc['actor'])}",
      f"- standard setup: torso {setup['torso_mass_kg']:g} kg, friction "
      f"{setup['friction']:g}, no randomization, no delay, flat floor; episodes of "
      f"{setup['episode_s']:g} s (recovery time counts from the control start, after "
      f"{setup['settle_s']:g} s of settling for dropped poses)",
  ]
  if any(c["experiment"] != "keystate" for c in doc["cells"]):
    lines.append("- entries: our success rate [95 % Wilson interval] · the paper's (Webots, 10 "
                 "trials; — where the paper reports none)")
  lines.append("")
  by_exp: dict[str, list[dict]] = {}
  for c in doc["cells"]:
    by_exp.setdefault(c["experiment"], []).append(c)
  for exp in proto_lib.EXPERIMENTS:
    cells = by_exp.get(exp)
    if not cells:
      continue
    lines += [f"## {EXPERIMENT_TITLES[exp]}", ""]
    if exp == "standard":
      header = [""] + [c["scenario"].capitalize() for c in cells]
      rows = [["Success rate"] + [_entry(c) for c in cells],
              ["Recovery time (s)"] + [
                  f"{_time(c['recovery_time_mean'], c['recovery_time_std'])} · "
                  f"{_time(*(c['paper_recovery_time'] or [None, None]))}" for c in cells]]
      lines += _table(header, rows)
      lines += ["", "The paper's recovery times are its real-robot measurements (20 trials)."]
    elif exp == "keystate":
      # Our diagnostic, not the paper's: one row per start state, no paper column.
      rows = [[f"`{c['scenario']}`", _pct(c["success_rate"]),
               f"{100 * c['ci95'][0]:.0f}–{100 * c['ci95'][1]:.0f}%",
               f"{c['successes']}/{c['trials']}",
               _time(c["recovery_time_mean"], c["recovery_time_std"]),
               _failures(c["failures"]), _within_rules(c)] for c in cells]
      lines += _table(["Start state", "Success rate", "95 % Wilson interval", "Successes",
                       "Recovery time (s)", "Failed trials ended",
                       "Successes within the stage's rules"], rows)
      lines += ["", "Every start state under the standard setup (no push, nominal mass and "
                "friction, no randomization); `stand` starts standing and succeeds by staying "
                "up. As in the paper, a trial ends only at the time limit (or a numerical "
                "blow-up). The last column is the stricter reading: the successes left if the "
                "termination rules of the policy's stage (`[stage.termination]`) ended trials "
                "as in training, and how many trials each rule would have ended before they "
                "stood. The paper reports no such table."]
    else:
      settings = list(dict.fromkeys(c["setting"] for c in cells))
      row_of = lambda c: proto_lib.table_row(exp, c["scenario"])
      row_names = list(dict.fromkeys(row_of(c) for c in cells))
      index = {(row_of(c), c["setting"]): c for c in cells}
      header = [""] + settings
      rows = [[name.capitalize()] + [_entry(index[(name, s)]) if (name, s) in index else ""
                                     for s in settings] for name in row_names]
      lines += _table(header, rows)
    failures = _sum_over(cells, lambda c: c["failures"])
    if exp != "keystate" and any(failures.values()):
      lines += ["", f"Failed trials ended: {_failures(failures)}."]
    met = _sum_over(cells, lambda c: c["within_rules"]["rule_met"])
    if exp != "keystate" and any(met.values()):
      within = sum(c["within_rules"]["successes"] for c in cells)
      lines += ["", f"Within the stage's termination rules: {within} of "
                f"{sum(c['successes'] for c in cells)} successes remain; trials the rules would "
                f"have ended before they stood: {_failures(met)}."]
    lines.append("")
  return "\n".join(lines)


def _write(out_dir: Path, contents: dict[str, str]) -> list[str]:
  """Writes each file atomically (a temporary sibling, fsynced, renamed into place)."""
  out_dir.mkdir(parents=True, exist_ok=True)
  paths = []
  for name, text in contents.items():
    path = out_dir / name
    write_atomic(path, text)
    paths.append(str(path.resolve()))
  return paths
