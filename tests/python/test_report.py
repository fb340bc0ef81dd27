"""`hifar report` (jax_env/evaluation/report.py) on synthetic run directories.

The runs are written the way `hifar train` and `hifar eval` write them (docs/contracts.md):
a manifest with two stages, metrics.jsonl lines with PPO and RMA adaptation phases, and two
evaluation directories of the same protocol (MJX and C MuJoCo: sim-to-sim) whose cells carry
the paper's numbers and Wilson intervals.
"""

import json
import math
import re
import struct
from pathlib import Path

import matplotlib.image
import pytest

from jax_env import facade
from jax_env.evaluation import report as report_lib

# The paper's success rates (prone, supine) per setting, tables of "Simulation Experiments".
PAPER = {
    "planar_push": (["50N", "100N", "150N", "200N", "250N", "300N"], [50, 100, 150, 200, 250, 300],
                    [1.0, 1.0, 1.0, 1.0, 0.8, 0.0], [1.0, 1.0, 1.0, 1.0, 1.0, 0.6]),
    "lateral_push": (["50N", "100N", "150N", "200N", "250N"], [50, 100, 150, 200, 250],
                     [1.0, 1.0, 1.0, 0.9, 0.1], [1.0, 1.0, 1.0, 1.0, 0.0]),
    "load": (["+2.4kg", "+5.9kg", "+9.4kg", "+11.7kg"], [2.4, 5.9, 9.4, 11.7],
             [1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]),
    "friction": (["0.8", "0.6", "0.4", "0.2", "0.1"], [0.8, 0.6, 0.4, 0.2, 0.1],
                 [1.0, 1.0, 1.0, 0.9, 0.0], [1.0, 1.0, 1.0, 1.0, 0.9]),
    "torque_limit": (["85%", "75%"], [0.85, 0.75], [1.0, 1.0], [1.0, 0.6]),
}
STAGES = (("planar", "completed", 40, 3), ("full", "threshold_missed", 30, 2))
STEPS_PER_ITER = 4096


def wilson(successes, trials, z=1.959963984540054):
  p = successes / trials
  denom = 1 + z * z / trials
  centre = (p + z * z / (2 * trials)) / denom
  half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
  return [max(0.0, centre - half), min(1.0, centre + half)]


def cell(experiment, scenario, setting, value, trials, successes, paper_rate, paper_time=None):
  times = successes > 0
  return {
      "experiment": experiment, "scenario": scenario, "setting": setting, "value": value,
      "trials": trials, "successes": successes, "success_rate": successes / trials,
      "ci95": wilson(successes, trials),
      "recovery_time_mean": 2.4 + 0.01 * successes if times else None,
      "recovery_time_std": 0.3 if times else None,
      "paper_success_rate": paper_rate, "paper_recovery_time": paper_time,
  }


def eval_json(backend, trials=20, penalty=0):
  """An eval.json of the paper protocol; `penalty` successes fewer per cell (sim-to-sim gap)."""
  cells = [
      cell("standard", "prone", "standard", None, trials, trials - penalty, 1.0, [2.875, 0.474]),
      cell("standard", "supine", "standard", None, trials, trials, 1.0, [2.711, 0.319]),
  ]
  for experiment, (labels, values, prone, supine) in PAPER.items():
    for scenario, rates in (("prone", prone), ("supine", supine)):
      for label, value, rate in zip(labels, values, rates):
        ours = max(0, min(trials, round(rate * trials) - penalty))
        cells.append(cell(experiment, scenario, label, value, trials, ours, rate))
  for state in ("lateral", "sitting", "crossed_legs", "random_drop"):
    cells.append(cell("random_initial", state, state, None, trials, trials - 1 - penalty, None))
  for scenario in ("prone", "supine"):
    for terrain in ("slope", "obstacle"):
      cells.append(cell("terrain", scenario, terrain, None, trials, 0 if terrain == "obstacle"
                        and scenario == "prone" else trials - 2, None))
  return {
      "format_version": 1, "protocol": "paper", "backend": backend, "seed": 0, "trials": trials,
      "checkpoint": "stages/full/checkpoints/000000286720", "stage": {"name": "full"},
      "env_steps": 286720, "versions": {"mujoco": "3.17.0"},
      "conditions": {"torso_mass": 11.7, "friction": 1.0}, "cells": cells,
  }


def metrics_line(stage, iteration, env_steps, phase, progress):
  """One metrics.jsonl object; `progress` in [0, 1] shapes the curves."""
  standing = 2.0 * min(1.0, math.floor(progress * 5) / 4)  # four step-like increases
  ended = iteration > 3
  losses = ({"adaptation": 0.5 * (1 - progress), "adaptation_before": 0.6 * (1 - progress)}
            if phase == "adaptation" else
            {"policy": -0.01 * progress, "value": 1.0 - 0.8 * progress, "mirror": 0.1,
             "kl": 0.01, "entropy": 12.0 - progress, "learning_rate": 3e-4, "total": 0.5,
             "action_std": 1.0, "clip_fraction": 0.1, "symmetry_error": 0.2})
  return {
      "stage": stage, "wall_time": 1.8e9 + 2.0 * iteration, "iteration": iteration,
      "env_steps": env_steps, "steps_per_s": 2000.0, "total_env_steps": 0, "phase": phase,
      "losses": losses,
      "rewards": {"standing": standing, "survival": 0.1, "orientation": -0.3 * (1 - progress)},
      "stand_rate": progress if ended else None,
      "recovery_time": 3.0 - progress if ended and progress > 0 else None,
      "episode_return": 10.0 + 50 * progress if ended else None,
  }


def stage_entry(name, status, env_steps):
  return {"name": name, "seed": 1, "status": status, "init_from": None,
          "init_checkpoint": None, "final_checkpoint": None, "env_steps": env_steps,
          "best_stand_rate": 0.9 if status == "completed" else None,
          "started_at": "2026-11-23T13:33:25.87867663Z",
          "ended_at": "2026-11-23T14:03:25.5Z"}


def write_run(root: Path, stages=STAGES, evals=(), name="synthetic") -> Path:
  run = root / name
  run.mkdir(parents=True)
  lines, entries = [], []
  for stage, status, ppo_iters, adapt_iters in stages:
    total = ppo_iters + adapt_iters
    for i in range(1, total + 1):
      phase = "ppo" if i <= ppo_iters else "adaptation"
      lines.append(metrics_line(stage, i, i * STEPS_PER_ITER, phase, i / total))
    entries.append(stage_entry(stage, status, total * STEPS_PER_ITER))
  manifest = {"format_version": 1, "name": name, "status": "completed", "seed": 11,
              "backend": "mjx", "git_commit": "abc", "started_at": "2026-11-23T13:33:25Z",
              "ended_at": "2026-11-23T14:33:25Z", "sessions": [], "stages": entries}
  (run / "manifest.json").write_text(json.dumps(manifest, indent=2))
  (run / "metrics.jsonl").write_text("".join(json.dumps(l) + "\n" for l in lines))
  for directory, data in evals:
    (run / "eval" / directory).mkdir(parents=True)
    (run / "eval" / directory / "eval.json").write_text(json.dumps(data))
  return run


def png_size(path: Path) -> tuple[int, int]:
  data = path.read_bytes()
  assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
  assert data[12:16] == b"IHDR"
  return struct.unpack(">II", data[16:24])


def expected(size) -> tuple[int, int]:
  return round(size[0] * report_lib.DPI), round(size[1] * report_lib.DPI)


def links(markdown: Path) -> list[str]:
  return re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown.read_text())


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
  root = tmp_path_factory.mktemp("report")
  run = write_run(root, evals=[("paper-mjx", eval_json("mjx")),
                               ("paper-native", eval_json("native", penalty=2))])
  result = facade.report({"run": str(run), "out_dir": str(run / "report")})
  return run, result


def test_every_plot_is_a_valid_png_of_the_expected_size(full_report):
  run, result = full_report
  plots = [Path(p) for p in result["plots"]]
  names = {p.name for p in plots}
  experiments = ["standard", *PAPER, "random_initial", "terrain"]
  assert names == {"learning_curves.png", "standing_reward.png", "losses.png",
                   *(f"eval_paper_{e}.png" for e in experiments)}
  sizes = {"learning_curves.png": report_lib.CURVES_SIZE,
           "standing_reward.png": report_lib.STANDING_SIZE, "losses.png": report_lib.LOSSES_SIZE}
  for path in plots:
    assert path.parent == run / "report"
    assert png_size(path) == expected(sizes.get(path.name, report_lib.EVAL_SIZE)), path.name
    pixels = matplotlib.image.imread(path)  # decodes the whole image
    assert pixels.shape[:2] == expected(sizes.get(path.name, report_lib.EVAL_SIZE))[::-1]
    assert pixels[..., :3].std() > 0.01, f"{path.name} is blank"
  assert not list((run / "report").glob(".*tmp*")), "temporary files left behind"


def test_markdown_links_every_plot_and_summarizes_the_run(full_report):
  run, result = full_report
  markdown = Path(result["markdown"])
  assert markdown == run / "report" / "report.md"
  targets = links(markdown)
  assert sorted(Path(markdown.parent / t).resolve() for t in targets) == \
      sorted(Path(p).resolve() for p in result["plots"])
  text = markdown.read_text()
  planar_steps, full_steps = (s[2] * STEPS_PER_ITER + s[3] * STEPS_PER_ITER for s in STAGES)
  assert f"| planar | completed | {planar_steps:,} | 43 |" in text
  assert f"| full | threshold_missed | {full_steps:,} | 32 |" in text
  assert f"{planar_steps + full_steps:,} in all" in text
  assert "Final stand rate: 100% (stage full" in text
  assert "Wall time: 1 h 00 min" in text
  assert "No evaluation yet" not in text
  assert "Sim-to-sim: evaluated with mjx and native" in text
  # The planar push table: prone row of the MJX evaluation, ours [CI] · paper.
  planar = text[text.index("#### Planar push"):text.index("#### Lateral push")]
  assert "| | 50N | 100N | 150N | 200N | 250N | 300N |" in planar
  row = next(l for l in planar.splitlines() if l.startswith("| prone · mjx | "))
  assert row.endswith("| 80% [58–92] · 80% | 0% [0–16] · 0% |"), row
  assert "| prone · native |" in text and "| supine · native |" in text
  assert "2.60 ± 0.30 s · 2.88 ± 0.47 s" in text  # standard prone, recovery time vs paper
  assert "`eval/paper-mjx`" in text and "`eval/paper-native`" in text


def test_stages_are_laid_end_to_end_and_a_resumed_iteration_counts_once(tmp_path):
  run = write_run(tmp_path, stages=(("planar", "completed", 4, 1), ("full", "running", 3, 0)))
  lines = (run / "metrics.jsonl").read_text().splitlines()
  # A resume re-logs planar's iteration 4 (same env steps, different value): the last wins.
  again = json.loads(lines[3])
  again["losses"]["value"] = 123.0
  lines.insert(5, json.dumps(again))
  (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
  records, bad = report_lib.read_metrics(run / "metrics.jsonl")
  spans = report_lib.stage_spans(report_lib.read_manifest(run), records)
  assert bad == 0
  assert [(s.name, s.start, s.env_steps) for s in spans] == [
      ("planar", 0, 5 * STEPS_PER_ITER), ("full", 5 * STEPS_PER_ITER, 3 * STEPS_PER_ITER)]
  assert spans[0].adaptation_start == 4 * STEPS_PER_ITER and spans[1].adaptation_start is None
  assert len(spans[0].records) == 5
  assert spans[0].records[3]["losses"]["value"] == 123.0


def test_a_run_without_evaluations_and_with_null_metrics_is_reported(tmp_path):
  run = write_run(tmp_path, stages=(("planar", "completed", 1, 0), ("full", "running", 2, 0)))
  # Every stand rate, recovery time and return null (no episode ended yet) ...
  lines = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
  for line in lines:
    line.update(stand_rate=None, recovery_time=None, episode_return=None)
  # ... and a last line half-written by a training still running.
  text = "".join(json.dumps(l) + "\n" for l in lines) + '{"stage": "full", "wall_ti'
  (run / "metrics.jsonl").write_text(text)
  manifest = json.loads((run / "manifest.json").read_text())
  manifest.update(status="running", ended_at=None)
  manifest["stages"][1].update(ended_at=None, env_steps=None)
  (run / "manifest.json").write_text(json.dumps(manifest))
  result = report_lib.report({"run": str(run), "out_dir": str(tmp_path / "out")})
  assert [Path(p).name for p in result["plots"]] == [
      "learning_curves.png", "standing_reward.png", "losses.png"]
  for p in result["plots"]:
    assert png_size(Path(p))[0] > 0
  md = Path(result["markdown"]).read_text()
  assert "No evaluation yet" in md
  assert "Stage planar has a single iteration" in md
  assert "No stand rate in any iteration" in md
  assert "1 line(s) of metrics.jsonl could not be read" in md
  assert "Final stand rate: — (no iteration reported one)" in md
  assert "Status: **running**" in md and " so far" in md
  assert f"| full | running | {2 * STEPS_PER_ITER:,} | 2 |" in md
  for target in links(Path(result["markdown"])):
    assert (tmp_path / "out" / target).is_file()


def test_a_run_that_has_not_trained_yet_has_no_plots(tmp_path):
  run = write_run(tmp_path, stages=())
  manifest = json.loads((run / "manifest.json").read_text())
  manifest["stages"] = [stage_entry("planar", "pending", None)]
  (run / "manifest.json").write_text(json.dumps(manifest))
  (run / "metrics.jsonl").unlink()
  result = report_lib.report({"run": str(run), "out_dir": str(run / "report")})
  assert result["plots"] == []
  assert "metrics.jsonl has no iterations yet" in Path(result["markdown"]).read_text()


def test_unreadable_eval_is_noted_and_a_report_can_be_remade(tmp_path):
  quick = eval_json("native", trials=8)
  quick.update(protocol="quick", cells=[c for c in quick["cells"]
                                        if c["experiment"] in ("standard", "planar_push")])
  run = write_run(tmp_path, stages=(("planar", "completed", 3, 1),),
                  evals=[("quick-native", quick)])
  (run / "eval" / "broken").mkdir()
  (run / "eval" / "broken" / "eval.json").write_text("{not json")
  first = report_lib.report({"run": str(run), "out_dir": str(run / "report")})
  second = report_lib.report({"run": str(run), "out_dir": str(run / "report")})
  assert first == second
  assert [Path(p).name for p in second["plots"]][3:] == ["eval_quick_standard.png",
                                                         "eval_quick_planar_push.png"]
  md = Path(second["markdown"]).read_text()
  assert "`eval/broken/eval.json` could not be read" in md
  assert "### Protocol quick" in md and "Sim-to-sim" not in md
  assert "eval_quick_planar_push.png" in md


def test_layout_puts_settings_or_scenarios_on_the_x_axis(tmp_path):
  evals = [report_lib.Evaluation(tmp_path / "a", eval_json("mjx")),
           report_lib.Evaluation(tmp_path / "b", eval_json("native"))]
  xs, series, mode = report_lib.experiment_layout(evals, "friction")
  assert (xs, mode) == (["0.8", "0.6", "0.4", "0.2", "0.1"], "setting")
  assert [s.label for s in series] == ["prone · mjx", "supine · mjx", "prone · native",
                                       "supine · native"]
  xs, series, mode = report_lib.experiment_layout(evals, "random_initial")
  assert (xs, mode) == (["lateral", "sitting", "crossed_legs", "random_drop"], "scenario")
  assert [s.label for s in series] == ["mjx", "native"]
  # Prone and supine share the standard setting, and a quick protocol may have one push force.
  xs, series, mode = report_lib.experiment_layout(evals, "standard")
  assert (xs, mode) == (["standard"], "setting")
  assert len(series) == 4
  quick = {**eval_json("mjx"), "cells": [c for c in eval_json("mjx")["cells"]
                                         if c["experiment"] == "planar_push"
                                         and c["setting"] == "150N"]}
  xs, series, mode = report_lib.experiment_layout(
      [report_lib.Evaluation(tmp_path / "q", quick)], "planar_push")
  assert (xs, mode, [s.label for s in series]) == (["150N"], "setting",
                                                   ["prone · mjx", "supine · mjx"])
  # Two evaluations with the same backend are told apart by their directory.
  twice = [report_lib.Evaluation(tmp_path / "a", eval_json("mjx")),
           report_lib.Evaluation(tmp_path / "b", eval_json("mjx"))]
  _, series, _ = report_lib.experiment_layout(twice, "random_initial")
  assert [s.label for s in series] == ["mjx (a)", "mjx (b)"]


def test_a_directory_without_manifest_is_refused(tmp_path):
  with pytest.raises(FileNotFoundError, match="is not a run directory \\(no manifest.json\\)"):
    report_lib.report({"run": str(tmp_path), "out_dir": str(tmp_path / "report")})
  assert not (tmp_path / "report").exists()


MONITORED = ("stand", "ksi_prone_1", "ksi_supine_1", "supine", "prone")


def _monitor(iteration, stage):
  """A deterministic monitor whose start states are learned one after the other (the step-like
  rises of key-state initialization); stage full adds a start state planar never saw."""
  rates = {name: (1.0 if iteration >= 6 * k else 0.0) for k, name in enumerate(MONITORED)}
  if stage == "full":
    rates["lateral"] = 0.25
  rates["prone"] = None if iteration == 5 else rates["prone"]  # a value the check could not get
  finite = [v for v in rates.values() if v is not None]
  return {"stand_rate": rates, "recovery_time": {n: None for n in rates},
          "max_height": {n: 0.7 for n in rates}, "mean_stand_rate": sum(finite) / len(finite)}


def test_monitor_stand_rate_per_start_state_is_plotted_across_stages(tmp_path):
  run = write_run(tmp_path, stages=(("planar", "completed", 30, 2), ("full", "running", 10, 0)))
  lines = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
  for line in lines:
    if line["iteration"] % 5 == 0 and line["phase"] == "ppo":
      line["monitor"] = _monitor(line["iteration"], line["stage"])
  # planar's adaptation phase ends with a monitor of the deployable actor (the PPO ones carry
  # no actor, as metrics written before the field existed: the privileged one).
  last_planar = [l for l in lines if l["stage"] == "planar"][-1]
  assert last_planar["phase"] == "adaptation"
  last_planar["monitor"] = {**_monitor(30, "planar"), "actor": "deployable"}
  (run / "metrics.jsonl").write_text("".join(json.dumps(l) + "\n" for l in lines))
  records, _ = report_lib.read_metrics(run / "metrics.jsonl")
  spans = report_lib.stage_spans(report_lib.read_manifest(run), records)
  assert report_lib.monitor_scenarios(spans) == [*MONITORED, "lateral"]
  # 7 planar + 2 full monitors: every start state's points but the two nulls, and the means.
  drawn = report_lib.plot_monitor(spans, tmp_path / "m.png")
  assert drawn == 7 * 5 + 2 * 6 - 2 + 9

  result = report_lib.report({"run": str(run), "out_dir": str(run / "report")})
  monitor = run / "report" / "monitor_stand_rate.png"
  assert str(monitor) in result["plots"]
  assert png_size(monitor) == expected(report_lib.MONITOR_SIZE)
  assert matplotlib.image.imread(monitor)[..., :3].std() > 0.01
  md = Path(result["markdown"]).read_text()
  assert "![stand rate per start state](monitor_stand_rate.png)" in md
  assert "| stage | env steps | actor | mean | `stand` | `ksi_prone_1` | `ksi_supine_1` | " \
         "`supine` | `prone` | `lateral` |" in md
  # planar's last monitor (the adaptation phase's): every start state learned; full's
  # (iteration 10, PPO).
  assert (f"| planar | {32 * STEPS_PER_ITER:,} | deployable | 100% | 100% | 100% | 100% | "
          "100% | 100% | — |") in md
  assert (f"| full | {10 * STEPS_PER_ITER:,} | privileged | 38% | 100% | 100% | 0% | 0% | 0% | "
          "25% |") in md
  assert "this plot is skipped" not in md


def test_without_a_monitor_the_plot_is_skipped_with_a_note(full_report):
  run, result = full_report
  assert not (run / "report" / "monitor_stand_rate.png").exists()
  md = Path(result["markdown"]).read_text()
  assert "No iteration of metrics.jsonl carries a `monitor`" in md
  assert "this plot is skipped" in md


def test_keystate_evaluation_is_plotted_per_start_state(tmp_path):
  states = ("stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1",
            "ksi_supine_2", "ksi_supine_3", "supine", "prone")
  cells = [cell("keystate", s, s, None, 8, 8 - i % 9, None) for i, s in enumerate(states)]
  data = {**eval_json("native", trials=8), "protocol": "keystate", "cells": cells}
  run = write_run(tmp_path, stages=(("planar", "completed", 3, 1),),
                  evals=[("keystate-native", data)])
  evals = [report_lib.Evaluation(run / "eval" / "keystate-native", data)]
  xs, series, mode = report_lib.experiment_layout(evals, "keystate")
  assert (xs, mode, [s.label for s in series]) == (list(states), "scenario", ["native"])
  result = report_lib.report({"run": str(run), "out_dir": str(run / "report")})
  plot = run / "report" / "eval_keystate_keystate.png"
  assert str(plot) in result["plots"]
  assert png_size(plot) == expected(report_lib.EVAL_SIZE)
  md = Path(result["markdown"]).read_text()
  assert "### Protocol keystate" in md
  assert "#### Start states of the key-state curriculum" in md
  assert "| | stand | ksi_prone_1 |" in md
  assert "| native | 100% [68–100] | 88% [53–98] |" in md  # no paper column
