"""How fast each physics path runs on this machine: `python -m jax_env.bench [--json]`.

For every batch size it measures, each in a fresh child process (so that peak memory and
compile time belong to that measurement alone):

- `raw_batch`:  `mujoco.batch.Batch` stepping the stage's model from the environment's reset
                states with the servo targets random actions would give, no JAX, no
                environment: the physical limit of C MuJoCo here;
- `native_env`: `FallRecoveryEnv(backend="native")`, jitted step with random actions; it also
                reports `paired`: itself and the raw batch timed in alternating slices of one
                time window (the ratio the 70 % target is judged on: robust on a shared CPU),
                and `host_fraction`, the share of its time spent in the C MuJoCo calls;
- `mjx_env`:    the same environment on MJX;
- `learner`:    `jax_env.learner.train.train_stage` iterations (rollout + PPO update), native
                backend; samples/s is env steps collected per second of a whole iteration.

Each result has `physics_steps_per_s`, `env_steps_per_s` (physics = env × substeps),
`compile_s` (the environment step's XLA compile; for the learner the first iteration's extra
time over a steady one; 0 for raw_batch, which compiles nothing) and `peak_rss_mb` (the child's
peak resident memory). Compiles are cold by default: the child does not read or write JAX's
persistent compilation cache, so `compile_s` is what a fresh machine pays (`use_cache=True`
to measure with the cache the caller configured).

What was not measured is listed under `skipped` with the reason (MJX above `mjx_max_batch`,
`--quick`, a learner that cannot run at that batch). `conditions` records what the numbers
depend on (cores, threads, load average before and after, versions), and `targets` the ratios
docs/contracts.md and issue 6 ask about (reported, never asserted).
"""

from __future__ import annotations

import argparse
import contextlib
import json as json_lib
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any, Callable, Sequence

from jax_env import paths

NAMES = ("raw_batch", "native_env", "mjx_env", "learner")
DEFAULT_BATCHES = (64, 256, 1024)
QUICK_BATCHES = (16,)
DEFAULT_CURRICULUM = paths.REPO_ROOT / "curricula" / "quickstart.toml"


def _peak_rss_mb() -> float:
  # ru_maxrss is KiB on Linux, bytes on macOS.
  scale = 1 / (1024 * 1024) if platform.system() == "Darwin" else 1 / 1024
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def load_stage(curriculum: str | os.PathLike | None = None, stage: str | None = None) -> dict:
  """A stage dict of a curriculum TOML (default: quickstart's first stage)."""
  path = Path(curriculum or DEFAULT_CURRICULUM)
  with open(path, "rb") as f:
    doc = tomllib.load(f)
  stages = doc.get("stage", [])
  if not stages:
    raise ValueError(f"{path}: no [[stage]] tables")
  if stage is None:
    return stages[0]
  for s in stages:
    if s.get("name") == stage:
      return s
  raise ValueError(f"{path}: no stage {stage!r}; valid: "
                   f"{', '.join(s.get('name', '?') for s in stages)}")


# ---------------------------------------------------------------------------------------------
# Single measurements (run in the child process).


def _timed_loop(fn: Callable[[int], Any], measure_s: float, min_iters: int) -> tuple[int, float]:
  """Calls fn(i) until measure_s passed and min_iters ran; (iterations, seconds)."""
  t0 = time.perf_counter()
  n = 0
  while n < min_iters or time.perf_counter() - t0 < measure_s:
    fn(n)
    n += 1
  return n, time.perf_counter() - t0


class _RawDriver:
  """`mujoco.batch` alone, one call of n_substeps per control step.

  It stands for the physics the environment runs, without the environment: it is loaded with
  the environment's own integration rows (the states `measure_env` reaches) and drives the
  servos the way the environment does with uniform random actions: controlled joints to
  base + scale·U(−clip, clip) (base = q or the stand pose, per the stage's action mapping), the
  others held at the stand pose, targets clipped to the joint ranges.
  """

  def __init__(self, env, batch: int, nthread: int, seed: int = 0):
    import numpy as np
    from mujoco import batch as mj_batch

    self.np = np
    self.env, self.batch = env, batch
    self.b = mj_batch.Batch(env.mj_model, batch, nthread)
    self.qpos, self.ctrl = self.b.bind("qpos"), self.b.bind("ctrl")
    self.idx = np.asarray(env.ctrl_idx)
    self.lo = np.asarray(env.lo, np.float64)
    self.hi = np.asarray(env.hi, np.float64)
    self.stand = np.asarray(env.q_stand, np.float64)
    self.target = np.tile(self.stand, (batch, 1))
    self.rng = np.random.default_rng(seed)
    self.current = env.stage.action.mapping == "current"

  def load(self, integration) -> None:
    from jax_env.physics.native_backend import integration_rows
    self.b.state[...] = integration_rows(integration)

  def step(self, _=None) -> None:
    np, a = self.np, self.env.stage.action
    u = self.rng.uniform(-a.clip, a.clip, (self.batch, self.idx.size))
    base = self.qpos[:, 7 + self.idx] if self.current else self.stand[self.idx]
    self.target[:, self.idx] = base + a.scale * u
    self.ctrl[...] = np.clip(self.target, self.lo, self.hi)
    self.b.step(nstep=self.env.n_substeps)


def measure_raw(stage_dict: dict, batch: int, measure_s: float, nthread: int | None) -> dict:
  """Raw `mujoco.batch` (see `_RawDriver`) from the native environment's reset states."""
  import jax
  import mujoco

  from jax_env.env import FallRecoveryEnv
  from jax_env.physics.native_backend import default_nthread

  env = FallRecoveryEnv(stage_dict, backend="native")
  start = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
  nthread = default_nthread() if nthread is None else nthread
  raw = _RawDriver(env, batch, nthread)
  raw.load(start.physics.integration)
  raw.step()
  n, dt = _timed_loop(raw.step, measure_s, 3)
  env_rate = n * batch / dt
  return {"physics_steps_per_s": env_rate * env.n_substeps, "env_steps_per_s": env_rate,
          "compile_s": 0.0, "nthread": nthread, "n_substeps": env.n_substeps, "seconds": dt,
          "iterations": n, "mujoco_version": mujoco.__version__}


def measure_env(stage_dict: dict, batch: int, backend: str, measure_s: float) -> dict:
  """The jitted environment step with uniform random actions (auto-resets included)."""
  import jax
  import jax.numpy as jnp

  from jax_env.env import FallRecoveryEnv

  env = FallRecoveryEnv(stage_dict, backend=backend)
  clip = env.stage.action.clip
  key = jax.random.PRNGKey(0)
  t0 = time.perf_counter()
  reset = jax.jit(env.reset).lower(jax.random.split(key, batch)).compile()
  reset_compile_s = time.perf_counter() - t0
  state = reset(jax.random.split(key, batch))

  def act_step(state, k):
    a = jax.random.uniform(k, (batch, env.action_size), minval=-clip, maxval=clip)
    return env.step(state, a)

  t0 = time.perf_counter()
  step = jax.jit(act_step).lower(state, key).compile()
  compile_s = time.perf_counter() - t0
  keys = jax.random.split(jax.random.PRNGKey(1), 1 << 16)
  for i in range(2):  # warm-up (first-call allocations, host batch creation)
    state = step(state, keys[i])
  jax.block_until_ready(state)
  holder = {"s": state, "ended": 0}

  def once(i):
    holder["s"] = step(holder["s"], keys[(i + 2) % keys.shape[0]])
    holder["ended"] += int(jnp.sum(holder["s"].done))  # also waits for the step

  stats0 = dict(getattr(env.backend, "stats", {}))
  n, dt = _timed_loop(once, measure_s, 3)
  env_rate = n * batch / dt
  out = {"physics_steps_per_s": env_rate * env.n_substeps, "env_steps_per_s": env_rate,
         "compile_s": compile_s, "reset_compile_s": reset_compile_s,
         "n_substeps": env.n_substeps, "seconds": dt, "iterations": n,
         "episodes_ended": holder["ended"]}
  if backend == "native":
    stats = env.backend.stats
    out["nthread"] = env.backend.nthread
    # Share of the wall time spent in the host calls (C MuJoCo plus their copies in and out);
    # the rest is the environment's JAX code around them.
    out["host_fraction"] = ((stats["step_s"] - stats0["step_s"]) +
                            (stats["init_s"] - stats0["init_s"])) / dt
    out["host_step_calls"] = stats["step_calls"] - stats0["step_calls"]
    out["host_init_calls"] = stats["init_calls"] - stats0["init_calls"]
    out["paired"] = _paired_with_raw(env, holder, step, keys, batch, measure_s)
  return out


def _paired_with_raw(env, holder, step, keys, batch: int, measure_s: float) -> dict:
  """Native env and raw batch in alternating slices of the same time window.

  The CPU may be shared, so throughput drifts from minute to minute; alternating short slices
  (the raw batch starting from the environment's current states each time) compares the two
  under the same conditions.
  """
  import jax

  raw = _RawDriver(env, batch, env.backend.nthread)
  env_n = raw_n = 0
  env_t = raw_t = 0.0
  slices = 4
  for s in range(slices):
    def once(i, s=s):
      holder["s"] = step(holder["s"], keys[(1000 + s * 997 + i) % keys.shape[0]])
      jax.block_until_ready(holder["s"].reward)
    n, dt = _timed_loop(once, measure_s / slices, 2)
    env_n, env_t = env_n + n, env_t + dt
    raw.load(holder["s"].physics.integration)
    n, dt = _timed_loop(raw.step, measure_s / slices, 2)
    raw_n, raw_t = raw_n + n, raw_t + dt
  sub = env.n_substeps
  env_rate = env_n * batch * sub / env_t
  raw_rate = raw_n * batch * sub / raw_t
  return {"env_physics_steps_per_s": env_rate, "raw_physics_steps_per_s": raw_rate,
          "ratio": env_rate / raw_rate}


def measure_learner(stage_dict: dict, batch: int, measure_s: float, backend: str) -> dict:
  """Whole training iterations (rollout + update) of the stage's learner at this batch."""
  from jax_env.env import FallRecoveryEnv
  from jax_env.learner.train import LearnerConfig, train_stage

  env = FallRecoveryEnv(stage_dict, backend=backend)
  config = LearnerConfig.from_stage(env.stage)
  times: list[float] = []
  rates: list[float] = []
  started = time.perf_counter()
  last = [started]

  def callback(progress: dict) -> str:
    now = time.perf_counter()
    times.append(now - last[0])
    rates.append(float(progress["steps_per_s"]))
    last[0] = now
    steady = now - started - times[0]
    # One compile iteration, then at least two steady ones and measure_s of them.
    return "interrupt" if len(times) >= 3 and steady >= measure_s else "continue"

  with tempfile.TemporaryDirectory(prefix="hifar-bench-") as tmp:
    train_stage(env, config, stage_dir=tmp, seed=0, num_envs=batch, callback=callback)
  if len(times) < 2:
    raise RuntimeError(f"the stage's budget ended after {len(times)} learner iteration(s) at "
                       f"batch {batch}; the learner needs at least 2 to time a steady one")
  steady_rates = rates[1:]
  samples = sum(steady_rates) / len(steady_rates)
  steady_iter = sum(times[1:]) / len(times[1:])
  return {"physics_steps_per_s": samples * env.n_substeps, "env_steps_per_s": samples,
          "samples_per_s": samples, "compile_s": max(times[0] - steady_iter, 0.0),
          "iterations": len(times), "backend": backend,
          "env_steps_per_iteration": batch * config.ppo.unroll_length}


def measure(name: str, batch: int, *, stage_dict: dict, measure_s: float,
            nthread: int | None = None, learner_backend: str = "native") -> dict:
  """One benchmark entry in this process."""
  if name == "raw_batch":
    out = measure_raw(stage_dict, batch, measure_s, nthread)
  elif name == "native_env":
    out = measure_env(stage_dict, batch, "native", measure_s)
  elif name == "mjx_env":
    out = measure_env(stage_dict, batch, "mjx", measure_s)
  elif name == "learner":
    out = measure_learner(stage_dict, batch, measure_s, learner_backend)
  else:
    raise ValueError(f"unknown benchmark {name!r}; valid: {', '.join(NAMES)}")
  return {"name": name, "batch": batch, **out, "peak_rss_mb": _peak_rss_mb()}


# ---------------------------------------------------------------------------------------------
# Orchestration.


def _learner_skip_reason(stage_dict: dict, batch: int) -> str | None:
  try:
    import jax_env.learner.train  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import
  except ImportError as err:
    return f"learner not importable: {err}"
  mb = int(stage_dict.get("ppo", {}).get("num_minibatches", 1))
  if batch % mb:
    return f"batch {batch} is not a multiple of ppo.num_minibatches = {mb}"
  return None


def _conditions(nthread: int | None) -> dict:
  import jax
  import mujoco

  from jax_env.physics.native_backend import default_nthread
  return {"cpu_count": os.cpu_count(), "cores_available": default_nthread(),
          "native_nthread": nthread or default_nthread(),
          "loadavg_start": list(os.getloadavg()), "platform": platform.platform(),
          "python": platform.python_version(), "jax": jax.__version__,
          "jax_backend": jax.default_backend(), "mujoco": mujoco.__version__}


def _run_child(name: str, batch: int, args: dict, timeout: float | None) -> dict:
  cmd = [sys.executable, "-m", "jax_env.bench", "--entry", name, "--batches", str(batch),
         "--measure-s", str(args["measure_s"]), "--learner-backend", args["learner_backend"],
         "--stage-json", json_lib.dumps(args["stage_dict"])]
  if args["nthread"] is not None:
    cmd += ["--nthread", str(args["nthread"])]
  if args["use_cache"]:
    cmd.append("--use-cache")
  proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
  lines = [l for l in proc.stdout.splitlines() if l.startswith("{")]
  if proc.returncode != 0 or not lines:
    tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
    raise RuntimeError(f"{name} at batch {batch} failed (exit {proc.returncode}): {tail}")
  return json_lib.loads(lines[-1])


def _targets(results: list[dict]) -> dict:
  by = {(r["name"], r["batch"]): r for r in results}
  out: dict[str, Any] = {}
  batches = sorted({r["batch"] for r in results})
  for b in batches:
    raw, nat, mjx = by.get(("raw_batch", b)), by.get(("native_env", b)), by.get(("mjx_env", b))
    if nat and "paired" in nat:  # same time window: robust on a shared CPU
      out[f"native_vs_raw_physics@{b}"] = nat["paired"]["ratio"]
    elif raw and nat:
      out[f"native_vs_raw_physics@{b}"] = nat["physics_steps_per_s"] / raw["physics_steps_per_s"]
    if raw and nat:
      out[f"native_vs_raw_physics_separate@{b}"] = (nat["physics_steps_per_s"] /
                                                     raw["physics_steps_per_s"])
    if nat and mjx:
      out[f"native_vs_mjx_env@{b}"] = nat["env_steps_per_s"] / mjx["env_steps_per_s"]
    if nat:
      out[f"native_compile_s@{b}"] = nat["compile_s"]
  goals = {"native_vs_raw_physics@256": (">=", 0.7), "native_vs_mjx_env": (">=", 8.0),
           "native_compile_s": ("<", 10.0)}
  met = {}
  for key, value in out.items():
    for goal, (op, limit) in goals.items():
      if key == goal or (key.startswith(goal + "@") and "@" not in goal):
        met[key] = bool(value >= limit) if op == ">=" else bool(value < limit)
  return {"values": out, "met": met,
          "goals": {"native_vs_raw_physics@256": ">= 0.7", "native_vs_mjx_env": ">= 8",
                    "native_compile_s": "< 10"}}


def run_bench(batches: Sequence[int] = DEFAULT_BATCHES, json: bool = False, *,
              quick: bool = False, names: Sequence[str] = NAMES,
              mjx_max_batch: int | None = None, measure_s: float | None = None,
              curriculum: str | os.PathLike | None = None, stage: str | None = None,
              nthread: int | None = None, learner_backend: str = "native",
              use_cache: bool = False, isolate: bool = True,
              timeout_s: float | None = None,
              progress: Callable[[dict], None] | None = None) -> dict:
  """Runs the benchmark; returns {"results": [...], "skipped": [...], "conditions", "targets"}.

  json=False prints a table row per result as it comes (the terminal form); json=True prints
  nothing (the caller prints the returned dict). quick measures briefly at batch 16 without
  MJX and the learner (their compiles alone take minutes on a CPU). isolate=False measures in
  this process (peak memory is then the process's, cumulative).
  """
  names = tuple(names)
  for n in names:
    if n not in NAMES:
      raise ValueError(f"unknown benchmark {n!r}; valid: {', '.join(NAMES)}")
  batches = tuple(int(b) for b in batches)
  if any(b <= 0 for b in batches):
    raise ValueError(f"batches must be positive, got {list(batches)}")
  if measure_s is None:
    measure_s = 1.0 if quick else 5.0
  stage_dict = load_stage(curriculum, stage)
  args = dict(stage_dict=stage_dict, measure_s=float(measure_s), nthread=nthread,
              learner_backend=learner_backend, use_cache=use_cache)
  conditions = _conditions(nthread)
  conditions.update(measure_s=float(measure_s), isolated=isolate, compile_cache=use_cache,
                    stage=stage_dict.get("name"),
                    curriculum=str(curriculum or DEFAULT_CURRICULUM))
  results, skipped = [], []
  if not json:
    print(f"{'name':<11} {'batch':>6} {'physics/s':>12} {'env/s':>10} {'compile s':>10} "
          f"{'peak MB':>8}", flush=True)
  for batch in batches:
    for name in names:
      reason = None
      if quick and name in ("mjx_env", "learner"):
        reason = "quick: MJX and learner compiles take minutes on a CPU"
      elif name == "mjx_env" and mjx_max_batch is not None and batch > mjx_max_batch:
        reason = f"mjx_max_batch = {mjx_max_batch}"
      elif name == "learner":
        reason = _learner_skip_reason(stage_dict, batch)
      if reason:
        skipped.append({"name": name, "batch": batch, "reason": reason})
        if not json:
          print(f"{name:<11} {batch:>6}  skipped: {reason}", flush=True)
        continue
      if isolate:
        r = _run_child(name, batch, args, timeout_s)
      else:
        r = measure(name, batch, stage_dict=stage_dict, measure_s=float(measure_s),
                    nthread=nthread, learner_backend=learner_backend)
      results.append(r)
      if progress is not None:
        progress(r)
      if not json:
        print(f"{name:<11} {batch:>6} {r['physics_steps_per_s']:>12.0f} "
              f"{r['env_steps_per_s']:>10.0f} {r['compile_s']:>10.2f} "
              f"{r['peak_rss_mb']:>8.0f}", flush=True)
  conditions["loadavg_end"] = list(os.getloadavg())
  out = {"results": results, "skipped": skipped, "conditions": conditions,
         "targets": _targets(results)}
  if not json:
    for key, value in out["targets"]["values"].items():
      mark = {True: " (target met)", False: " (target missed)"}.get(
          out["targets"]["met"].get(key), "")
      print(f"{key}: {value:.3g}{mark}")
    print(f"conditions: {conditions['cores_available']} cores, native threads "
          f"{conditions['native_nthread']}, load average {conditions['loadavg_start'][0]:.2f} "
          f"→ {conditions['loadavg_end'][0]:.2f}")
  return out


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(prog="python -m jax_env.bench", description=__doc__.split("\n")[0])
  p.add_argument("--json", action="store_true", help="print one JSON document, no table")
  p.add_argument("--batches", type=int, nargs="+", default=None,
                 help=f"batch sizes (default {' '.join(map(str, DEFAULT_BATCHES))}; "
                      f"--quick: {' '.join(map(str, QUICK_BATCHES))})")
  p.add_argument("--quick", action="store_true",
                 help="short measurements, no MJX and no learner")
  p.add_argument("--only", nargs="+", choices=NAMES, default=None, help="entries to run")
  p.add_argument("--mjx-max-batch", type=int, default=None,
                 help="skip mjx_env above this batch (MJX at 1024 is slow on a CPU)")
  p.add_argument("--measure-s", type=float, default=None, help="seconds per measurement")
  p.add_argument("--curriculum", default=None, help="curriculum TOML (default quickstart)")
  p.add_argument("--stage", default=None, help="stage name (default the first)")
  p.add_argument("--nthread", type=int, default=None, help="native threads (default cores)")
  p.add_argument("--learner-backend", default="native", choices=("native", "mjx"))
  p.add_argument("--use-cache", action="store_true",
                 help="let compiles use JAX's persistent compilation cache")
  p.add_argument("--in-process", action="store_true", help="no child processes")
  p.add_argument("--entry", choices=NAMES, help=argparse.SUPPRESS)
  p.add_argument("--stage-json", help=argparse.SUPPRESS)
  a = p.parse_args(argv)

  if a.entry:  # child: one measurement, one JSON line
    if not a.use_cache:
      import jax
      jax.config.update("jax_enable_compilation_cache", False)
    stage_dict = json_lib.loads(a.stage_json) if a.stage_json else load_stage(a.curriculum,
                                                                              a.stage)
    r = measure(a.entry, a.batches[0], stage_dict=stage_dict, measure_s=a.measure_s or 5.0,
                nthread=a.nthread, learner_backend=a.learner_backend)
    print(json_lib.dumps(r), flush=True)
    return 0

  batches = a.batches or (QUICK_BATCHES if a.quick else DEFAULT_BATCHES)
  # With --json, stdout carries exactly one JSON document: anything imported libraries print
  # (mujoco.mjx prints "Failed to import warp" on machines without it) goes to stderr.
  quiet = contextlib.redirect_stdout(sys.stderr) if a.json else contextlib.nullcontext()
  with quiet:
    out = run_bench(batches, json=a.json, quick=a.quick, names=a.only or NAMES,
                    mjx_max_batch=a.mjx_max_batch, measure_s=a.measure_s,
                    curriculum=a.curriculum, stage=a.stage, nthread=a.nthread,
                    learner_backend=a.learner_backend, use_cache=a.use_cache,
                    isolate=not a.in_process)
  if a.json:
    print(json_lib.dumps(out, indent=2))
  return 0


if __name__ == "__main__":
  sys.exit(main())
