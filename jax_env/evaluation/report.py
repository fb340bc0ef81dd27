"""`hifar report`: PNG plots and a markdown summary of a run directory.

Inputs (docs/contracts.md, "facade.report"): `<run>/manifest.json` (stages, statuses, env
steps), `<run>/metrics.jsonl` (one object per training iteration) and every
`<run>/eval/*/eval.json` (the evaluator's cells). The report only reads the run, so it may be
made while `hifar train` is still writing it: a half-written last metrics line is skipped and
a stage still running is drawn as far as it got.

Training curves are drawn against the run's cumulative env steps: stage k starts where stage
k-1 ended (its recorded env steps, the PPO budget plus the RMA adaptation steps), so the whole
curriculum reads left to right with a boundary and the stage's name at every change, and the
RMA adaptation phase of each stage shaded. Lines that carry a `monitor` (the deterministic
per-start-state check of `[stage.monitor]`) add the stand rate of every start state on the same
axis, the paper's step-like rises of key-state initialization (its Fig. 4); without one that
plot is skipped with a note. Evaluations are drawn per protocol and experiment:
success rate with its 95% Wilson interval and recovery time (mean ± std) against the
setting, one series per fall scenario and evaluated backend (sim-to-sim when a policy was
evaluated in both MJX and C MuJoCo), the paper's numbers as hollow markers.

Matplotlib is used through `Figure` and the Agg canvas only (no pyplot, no display), and every
file is written to a temporary sibling and renamed into place.
"""

from __future__ import annotations

import dataclasses
import json
import math
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from jax_env import facade_requests
from jax_env.files import write_atomic

DPI = 150
CURVES_SIZE = (10.0, 9.0)  # inches: three stacked panels
STANDING_SIZE = (10.0, 4.5)
LOSSES_SIZE = (12.0, 7.0)  # 2 × 3 panels
EVAL_SIZE = (10.0, 7.5)  # success rate over recovery time
MONITOR_SIZE = (11.0, 5.0)  # stand rate per start state, legend at the right

LOSS_PANELS = (
    ("policy", "policy loss"),
    ("value", "value loss"),
    ("mirror", "mirror (symmetry) loss"),
    ("kl", "KL(old ‖ new)"),
    ("entropy", "entropy"),
    ("adaptation", "RMA adaptation loss"),
)

EXPERIMENTS = {
    # experiment: (title, x-axis label)
    "standard": ("Standard supine and prone recovery",
                 "nominal setup (torso 11.7 kg, friction 1.0, no disturbance)"),
    "planar_push": ("Planar push (along the torso, from 0.8 s for 200 ms)", "push force"),
    "lateral_push": ("Lateral push (leftward, from 0.8 s for 200 ms)", "push force"),
    "load": ("Load: extra torso mass", "extra torso mass"),
    "friction": ("Floor friction", "friction coefficient"),
    "torque_limit": ("Torque limit", "torque limit (fraction of nominal)"),
    "random_initial": ("Random initial states", "initial state"),
    "terrain": ("Stage-2 terrains", "terrain"),
    "keystate": ("Start states of the key-state curriculum (nominal conditions)",
                 "start state"),
}

SCENARIO_COLORS = {"prone": "tab:blue", "supine": "tab:orange"}
OTHER_COLORS = ("tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
                "tab:cyan", "tab:gray")
BACKEND_STYLES = {"mjx": ("o", "-"), "native": ("s", "--")}
OTHER_STYLES = (("^", ":"), ("v", "-."), ("D", "-"))


# --------------------------------------------------------------------------------------------
# Reading the run


@dataclasses.dataclass(frozen=True)
class StageSpan:
  """One curriculum stage placed on the run's cumulative env-step axis."""

  name: str
  status: str
  start: int  # cumulative env steps before the stage
  env_steps: int  # steps taken in the stage (0 if it has not started)
  adaptation_start: int | None  # within-stage env steps where RMA adaptation began
  records: tuple  # its metrics lines, deduplicated, by env steps
  manifest: dict  # its manifest entry ({} for a stage only metrics.jsonl names)

  @property
  def end(self) -> int:
    return self.start + self.env_steps


@dataclasses.dataclass(frozen=True)
class Evaluation:
  """One `<run>/eval/<dir>/eval.json`."""

  directory: Path
  data: dict

  @property
  def protocol(self) -> str:
    return str(self.data.get("protocol", "?"))

  @property
  def backend(self) -> str:
    return str(self.data.get("backend", "?"))


def read_manifest(run: Path) -> dict:
  path = run / "manifest.json"
  if not path.is_file():
    raise FileNotFoundError(f"{run} is not a run directory (no manifest.json)")
  try:
    manifest = json.loads(path.read_text())
  except json.JSONDecodeError as e:
    raise ValueError(f"{path}: invalid JSON: {e}") from None
  if not isinstance(manifest, dict) or not isinstance(manifest.get("stages", []), list):
    raise ValueError(f"{path}: not a hifar manifest (expected an object with a \"stages\" list)")
  return manifest


def read_metrics(path: Path) -> tuple[list[dict], int]:
  """The metrics lines that parse, and how many did not (a line being written, say)."""
  if not path.is_file():
    return [], 0
  records, bad = [], 0
  with open(path, encoding="utf-8", errors="replace") as f:
    for line in f:
      line = line.strip()
      if not line:
        continue
      try:
        record = json.loads(line)
      except json.JSONDecodeError:
        bad += 1
        continue
      if isinstance(record, dict) and isinstance(record.get("stage"), str) and \
          _number(record.get("env_steps")) is not None:
        records.append(record)
      else:
        bad += 1
  return records, bad


def stage_spans(manifest: dict, records: Sequence[dict]) -> list[StageSpan]:
  """The manifest's stages (then any stage only metrics.jsonl names) on one env-step axis.

  A resumed stage logs again the iterations after its last checkpoint: for every env-step
  count the line written last wins.
  """
  entries = [s for s in manifest.get("stages", []) if isinstance(s, dict) and "name" in s]
  names = [str(s["name"]) for s in entries]
  for r in records:
    if r["stage"] not in names:
      names.append(r["stage"])
  by_manifest = {str(s["name"]): s for s in entries}
  spans, start = [], 0
  for name in names:
    latest: dict[int, dict] = {}
    for r in records:
      if r["stage"] == name:
        latest[int(r["env_steps"])] = r
    stage_records = tuple(latest[k] for k in sorted(latest))
    entry = by_manifest.get(name, {})
    steps = max([int(r["env_steps"]) for r in stage_records] +
                [int(_number(entry.get("env_steps")) or 0)])
    ppo = [int(r["env_steps"]) for r in stage_records if r.get("phase") != "adaptation"]
    adaptation = any(r.get("phase") == "adaptation" for r in stage_records)
    spans.append(StageSpan(
        name=name, status=str(entry.get("status", "unknown")), start=start, env_steps=steps,
        adaptation_start=(max(ppo) if ppo else 0) if adaptation else None,
        records=stage_records, manifest=entry))
    start += steps
  return spans


def read_evaluations(run: Path) -> tuple[list[Evaluation], list[str]]:
  """Every readable `<run>/eval/*/eval.json`, and a note for each one that is not."""
  evals, notes = [], []
  root = run / "eval"
  if not root.is_dir():
    return evals, notes
  for path in sorted(root.glob("*/eval.json")):
    try:
      data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
      notes.append(f"`{_rel(path, run)}` could not be read ({_one_line(e)}); it is left out.")
      continue
    if not isinstance(data, dict) or not isinstance(data.get("cells"), list):
      notes.append(f"`{_rel(path, run)}` has no \"cells\" list; it is left out.")
      continue
    evals.append(Evaluation(directory=path.parent, data=data))
  return evals, notes


# --------------------------------------------------------------------------------------------
# Small helpers


def _number(value: Any) -> float | None:
  """A finite float, or None (null, NaN, a string, ...)."""
  if isinstance(value, bool) or not isinstance(value, (int, float)):
    return None
  return float(value) if math.isfinite(value) else None


def _one_line(e: BaseException) -> str:
  text = str(e).strip().splitlines()
  return text[-1] if text else type(e).__name__


def _rel(path: Path, base: Path) -> str:
  try:
    return str(path.relative_to(base))
  except ValueError:
    return str(path)


def _steps_text(n: float) -> str:
  """1234 → "1.2k", 200_000_000 → "200M"."""
  for div, unit in ((1e9, "B"), (1e6, "M"), (1e3, "k")):
    if abs(n) >= div:
      text = f"{n / div:.3g}"
      return f"{text}{unit}"
  return f"{n:.0f}"


def _duration_text(seconds: float | None) -> str:
  if seconds is None or not math.isfinite(seconds) or seconds < 0:
    return "—"
  if seconds < 60:
    return f"{seconds:.1f} s"
  minutes, s = divmod(int(round(seconds)), 60)
  if minutes < 60:
    return f"{minutes} min {s:02d} s"
  hours, minutes = divmod(minutes, 60)
  return f"{hours} h {minutes:02d} min"


def _timestamp(text: Any) -> float | None:
  if not isinstance(text, str):
    return None
  try:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()
  except ValueError:
    return None


def _percent(x: float | None) -> str:
  return "—" if x is None else f"{100 * x:.0f}%"


def _column(span: StageSpan, get: Callable[[dict], Any]) -> tuple[np.ndarray, np.ndarray]:
  """(cumulative env steps, value) of the stage's lines where `get` gives a finite number."""
  xs, ys = [], []
  for r in span.records:
    try:
      y = _number(get(r))
    except (KeyError, TypeError, AttributeError):
      y = None
    if y is not None:
      xs.append(span.start + int(r["env_steps"]))
      ys.append(y)
  return np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)


def _smooth(y: np.ndarray) -> np.ndarray:
  """A centred moving average over ~2% of the points (identity for short curves)."""
  window = max(1, len(y) // 50)
  if window < 3:
    return y
  kernel = np.ones(window) / window
  padded = np.pad(y, (window // 2, window - 1 - window // 2), mode="edge")
  return np.convolve(padded, kernel, mode="valid")


def _save(fig, path: Path) -> None:
  from matplotlib.backends.backend_agg import FigureCanvasAgg
  FigureCanvasAgg(fig)
  write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI))


def _figure(size: tuple[float, float], rows: int, cols: int, sharex: bool = True):
  from matplotlib.figure import Figure
  fig = Figure(figsize=size, dpi=DPI, layout="constrained")
  axes = fig.subplots(rows, cols, sharex=sharex, squeeze=False)
  return fig, axes


def _steps_axis(ax, spans: Sequence[StageSpan], label: bool = True) -> None:
  """Stage boundaries, stage names, shaded adaptation phases and an env-step formatter."""
  from matplotlib.ticker import FuncFormatter
  from matplotlib.transforms import blended_transform_factory
  total = max([s.end for s in spans] + [1])
  ax.set_xlim(0, total)
  ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: _steps_text(v)))
  top = blended_transform_factory(ax.transData, ax.transAxes)
  shaded = False
  for i, span in enumerate(spans):
    if span.env_steps <= 0:
      continue
    if i > 0:
      ax.axvline(span.start, color="0.3", linestyle="--", linewidth=1.0)
    ax.text(span.start + 0.01 * total, 0.97, span.name, transform=top, ha="left", va="top",
            fontsize=9, color="0.2",
            bbox=dict(boxstyle="round,pad=0.2", facecolor="white", edgecolor="0.7", alpha=0.8))
    if span.adaptation_start is not None and span.adaptation_start < span.env_steps:
      ax.axvspan(span.start + span.adaptation_start, span.end, color="0.85", alpha=0.6,
                 linewidth=0, label=None if shaded else "RMA adaptation")
      shaded = True
  if label:
    ax.set_xlabel("env steps (cumulative over stages)")
  ax.grid(True, alpha=0.3)


def _cycle_color(i: int) -> str:
  return f"C{i % 10}"


def _no_data(ax, text: str) -> None:
  ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=10,
          color="0.4")


def _plot_stage_series(ax, spans: Sequence[StageSpan], get: Callable[[dict], Any],
                       smooth: bool = False) -> int:
  """One line per stage (its own color); returns the number of points drawn."""
  drawn = 0
  for i, span in enumerate(spans):
    x, y = _column(span, get)
    if len(x) == 0:
      continue
    drawn += len(x)
    color = _cycle_color(i)
    marker = "o" if len(x) <= 60 else None
    if smooth and len(x) > 150:
      ax.plot(x, y, color=color, alpha=0.25, linewidth=0.8)
      ax.plot(x, _smooth(y), color=color, linewidth=1.8, label=span.name)
    else:
      ax.plot(x, y, color=color, linewidth=1.5, marker=marker, markersize=3, label=span.name)
  return drawn


# --------------------------------------------------------------------------------------------
# Training plots


def plot_learning_curves(spans: Sequence[StageSpan], path: Path) -> dict[str, int]:
  """Episode return, stand rate and recovery time of every stage; points drawn per panel."""
  fig, axes = _figure(CURVES_SIZE, 3, 1)
  panels = (
      ("episode_return", "episode return", lambda r: r["episode_return"], 1.0,
       "no episode return reported"),
      ("stand_rate", "stand rate (%)", lambda r: r["stand_rate"], 100.0,
       "no stand rate reported (no episode ended)"),
      ("recovery_time", "recovery time (s)", lambda r: r["recovery_time"], 1.0,
       "no recovery time reported (no episode reached stable standing)"),
  )
  counts = {}
  for index, (key, ylabel, get, scale, empty) in enumerate(panels):
    ax = axes[index, 0]
    counts[key] = _plot_stage_series(
        ax, spans, lambda r, get=get, scale=scale: _scaled(get(r), scale), smooth=True)
    if counts[key] == 0:
      _no_data(ax, empty)
    ax.set_ylabel(ylabel)
    _steps_axis(ax, spans, label=index == len(panels) - 1)
  if counts["stand_rate"]:
    axes[1, 0].set_ylim(-5, 105)
  _legend(axes[0, 0])
  fig.suptitle("Learning curves of every stage", fontsize=13)
  _save(fig, path)
  return counts


def _scaled(value: Any, scale: float) -> float | None:
  v = _number(value)
  return None if v is None else v * scale


def plot_standing_reward(spans: Sequence[StageSpan], path: Path) -> int:
  """The standing term's mean weighted per-step reward (the paper's training-analysis curve)."""
  fig, axes = _figure(STANDING_SIZE, 1, 1)
  ax = axes[0, 0]
  drawn = _plot_stage_series(ax, spans, lambda r: r["rewards"]["standing"], smooth=True)
  if drawn == 0:
    _no_data(ax, "no standing reward logged")
  ax.set_ylabel("standing reward\n(mean weighted per step)")
  _steps_axis(ax, spans)
  _legend(ax)
  ax.set_title("Training analysis: standing reward", fontsize=13)
  _save(fig, path)
  return drawn


def monitor_scenarios(spans: Sequence[StageSpan]) -> list[str]:
  """The start states of every `monitor` in metrics.jsonl, in order of first appearance."""
  names: list[str] = []
  for span in spans:
    for r in span.records:
      rates = _monitor_rates(r)
      names += [n for n in rates if n not in names]
  return names


def _monitor_rates(record: dict) -> dict:
  monitor = record.get("monitor")
  rates = monitor.get("stand_rate") if isinstance(monitor, dict) else None
  return rates if isinstance(rates, dict) else {}


def _monitor_mean(record: dict) -> Any:
  monitor = record.get("monitor")
  return monitor.get("mean_stand_rate") if isinstance(monitor, dict) else None


def plot_monitor(spans: Sequence[StageSpan], path: Path) -> int:
  """The deterministic monitor's stand rate per start state (one line each, the same color in
  every stage, not joined across a stage boundary) and their mean; points drawn."""
  from matplotlib import colormaps
  fig, axes = _figure(MONITOR_SIZE, 1, 1)
  ax = axes[0, 0]
  names = monitor_scenarios(spans)
  palette = colormaps["tab10" if len(names) <= 10 else "tab20"]
  drawn = 0
  series = [(name, lambda r, name=name: _scaled(_monitor_rates(r).get(name), 100.0),
             dict(color=palette(i % palette.N), linewidth=1.4, marker="o", markersize=3))
            for i, name in enumerate(names)]
  series.append(("mean", lambda r: _scaled(_monitor_mean(r), 100.0),
                 dict(color="black", linewidth=2.2, linestyle="--")))
  for name, get, style in series:
    labelled = False
    for span in spans:
      x, y = _column(span, get)
      if len(x) == 0:
        continue
      drawn += len(x)
      ax.plot(x, y, label=None if labelled else name,
              **({**style, "marker": None} if len(x) > 60 else style))
      labelled = True
  ax.set_ylim(-5, 112)  # room for the stage names above 100 %
  ax.set_ylabel("stand rate (%)\n(deterministic policy)")
  _steps_axis(ax, spans)
  _legend_outside(ax)
  ax.set_title("Stand rate per start state (deterministic monitor)", fontsize=13)
  _save(fig, path)
  return drawn


def plot_losses(spans: Sequence[StageSpan], path: Path) -> dict[str, int]:
  fig, axes = _figure(LOSSES_SIZE, 2, 3)
  counts = {}
  for index, (key, title) in enumerate(LOSS_PANELS):
    ax = axes.flat[index]
    counts[key] = _plot_stage_series(ax, spans, lambda r, key=key: r["losses"][key])
    if counts[key] == 0:
      _no_data(ax, f"no {key} loss logged")
    ax.set_title(title, fontsize=11)
    _steps_axis(ax, spans, label=index >= axes.shape[1])
  _legend(axes[0, 0])
  fig.suptitle("Losses per stage", fontsize=13)
  _save(fig, path)
  return counts


def _legend(ax) -> None:
  handles, labels = ax.get_legend_handles_labels()
  if handles:
    ax.legend(loc="lower right", fontsize=9, framealpha=0.85)


# --------------------------------------------------------------------------------------------
# Evaluation plots


@dataclasses.dataclass(frozen=True)
class EvalSeries:
  """The cells of one experiment of one evaluation, for one scenario (or all of them)."""

  label: str
  color: str
  marker: str
  linestyle: str
  cells: dict  # x label -> cell


def _series_labels(evals: Sequence[Evaluation]) -> list[str]:
  """The backend, or backend and directory where one protocol has a backend twice."""
  backends = [e.backend for e in evals]
  return [e.backend if backends.count(e.backend) == 1 else f"{e.backend} ({e.directory.name})"
          for e in evals]


def _cells(evaluation: Evaluation, experiment: str) -> list[dict]:
  return [c for c in evaluation.data["cells"]
          if isinstance(c, dict) and c.get("experiment") == experiment]


def _unique(values: Iterable[str]) -> list[str]:
  out: list[str] = []
  for v in values:
    if v not in out:
      out.append(v)
  return out


def experiment_layout(evals: Sequence[Evaluation], experiment: str):
  """x labels and series for one experiment over several evaluations.

  Usually scenarios share settings (prone and supine under each push force, load, ...): the x
  axis is the setting and each scenario × backend is a series, the rows of the paper's
  tables. When every scenario has a single setting of its own (random initial states: one
  scenario per state) the x axis is the scenario and each backend is a series.
  """
  labels = _series_labels(evals)
  all_cells = [c for e in evals for c in _cells(e, experiment)]
  scenarios = _unique(str(c.get("scenario")) for c in all_cells)
  pairs = _unique((str(c.get("scenario")), str(c.get("setting"))) for c in all_cells)
  settings = _unique(setting for _, setting in pairs)
  series: list[EvalSeries] = []
  if len(scenarios) > 1 and len(pairs) == len(scenarios) == len(settings):
    def x_of(c):
      s, setting = str(c.get("scenario")), str(c.get("setting"))
      return s if setting in (s, "None", "") else f"{s}\n{setting}"
    xs = _unique(x_of(c) for c in all_cells)
    for i, (e, label) in enumerate(zip(evals, labels)):
      marker, _ = _backend_style(e.backend, i)
      series.append(EvalSeries(label=label, color=_cycle_color(i), marker=marker,
                               linestyle="none", cells={x_of(c): c for c in _cells(e, experiment)}))
    return xs, series, "scenario"
  for i, (e, label) in enumerate(zip(evals, labels)):
    marker, style = _backend_style(e.backend, i)
    for j, scenario in enumerate(scenarios):
      cells = {str(c.get("setting")): c for c in _cells(e, experiment)
               if str(c.get("scenario")) == scenario}
      if cells:
        series.append(EvalSeries(label=f"{scenario} · {label}", color=_scenario_color(scenario, j),
                                 marker=marker, linestyle=style, cells=cells))
  return settings, series, "setting"


def _scenario_color(scenario: str, index: int) -> str:
  return SCENARIO_COLORS.get(scenario, OTHER_COLORS[index % len(OTHER_COLORS)])


def _backend_style(backend: str, index: int) -> tuple[str, str]:
  return BACKEND_STYLES.get(backend, OTHER_STYLES[index % len(OTHER_STYLES)])


def plot_experiment(evals: Sequence[Evaluation], protocol: str, experiment: str,
                    path: Path) -> None:
  """Success rate (Wilson 95% CI) and recovery time (mean ± std) against the setting."""
  xs, series, mode = experiment_layout(evals, experiment)
  fig, axes = _figure(EVAL_SIZE, 2, 1)
  success_ax, time_ax = axes[:, 0]
  n = len(series)
  width = min(0.3, 0.6 / max(n, 1))
  paper_drawn: set[str] = set()
  labelled: set[tuple[str, str]] = set()  # one legend entry per (axes, paper series)

  def once(axis: str, label: str) -> str | None:
    if (axis, label) in labelled:
      return None
    labelled.add((axis, label))
    return label

  time_points = 0
  for k, s in enumerate(series):
    offset = (k - (n - 1) / 2) * width
    pos, rate, low, high, tpos, tmean, tstd = [], [], [], [], [], [], []
    for i, x in enumerate(xs):
      cell = s.cells.get(x)
      if cell is None:
        continue
      r = _number(cell.get("success_rate"))
      ci = cell.get("ci95") or [None, None]
      if r is not None:
        lo, hi = _number(ci[0]) if len(ci) > 0 else None, _number(ci[1]) if len(ci) > 1 else None
        pos.append(i + offset)
        rate.append(100 * r)
        low.append(100 * (r - lo) if lo is not None else 0.0)
        high.append(100 * (hi - r) if hi is not None else 0.0)
      m = _number(cell.get("recovery_time_mean"))
      if m is not None:
        tpos.append(i + offset)
        tmean.append(m)
        tstd.append(_number(cell.get("recovery_time_std")) or 0.0)
    if pos:
      success_ax.errorbar(pos, rate, yerr=[low, high], color=s.color, marker=s.marker,
                          linestyle=s.linestyle, capsize=3, markersize=6, label=s.label)
    if tpos:
      time_points += len(tpos)
      time_ax.errorbar(tpos, tmean, yerr=tstd, color=s.color, marker=s.marker,
                       linestyle=s.linestyle, capsize=3, markersize=6, label=s.label)
  # The paper's numbers: one hollow marker per (scenario, setting), whatever the backend.
  for x_index, x in enumerate(xs):
    for s in series:
      cell = s.cells.get(x)
      if cell is None:
        continue
      color = s.color if mode == "setting" else "black"
      key = f"{cell.get('scenario')}|{x}"
      if key in paper_drawn:
        continue
      paper_drawn.add(key)
      label_key = f"paper ({cell.get('scenario')})" if mode == "setting" else "paper"
      pr = _number(cell.get("paper_success_rate"))
      if pr is not None:
        success_ax.plot([x_index], [100 * pr], linestyle="none", marker="D", markersize=10,
                        markerfacecolor="none", markeredgecolor=color, markeredgewidth=1.6,
                        label=once("success", label_key))
      pt = cell.get("paper_recovery_time")
      if isinstance(pt, (list, tuple)) and len(pt) == 2 and _number(pt[0]) is not None:
        time_ax.errorbar([x_index], [pt[0]], yerr=[_number(pt[1]) or 0.0], linestyle="none",
                         marker="D", markersize=10, markerfacecolor="none",
                         markeredgecolor=color, ecolor=color, capsize=5, elinewidth=0.8,
                         label=once("time", label_key))
  title, xlabel = EXPERIMENTS.get(experiment, (experiment.replace("_", " "), mode))
  for ax in (success_ax, time_ax):
    ax.set_xticks(range(len(xs)), xs)
    ax.set_xlim(-0.6, len(xs) - 0.4)
    ax.grid(True, alpha=0.3)
  success_ax.set_ylim(-5, 108)
  success_ax.set_ylabel("success rate (%)\n(95% Wilson CI)")
  time_ax.set_ylabel("recovery time (s)\n(mean ± std over successes)")
  time_ax.set_xlabel(xlabel)
  if time_points == 0:
    _no_data(time_ax, "no successful recovery: no recovery time")
  _legend_outside(success_ax)
  _legend_outside(time_ax)
  trials = _unique(str(e.data.get("trials")) for e in evals)
  fig.suptitle(f"{title} — protocol {protocol}, {'/'.join(trials)} trials per cell", fontsize=12)
  _save(fig, path)


def _legend_outside(ax) -> None:
  handles, labels = ax.get_legend_handles_labels()
  if handles:
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)


# --------------------------------------------------------------------------------------------
# Markdown


def _stage_wall_time(span: StageSpan) -> float | None:
  start, end = _timestamp(span.manifest.get("started_at")), _timestamp(span.manifest.get("ended_at"))
  times = [t for t in (_number(r.get("wall_time")) for r in span.records) if t is not None]
  if start is not None and end is not None:
    return end - start
  if start is not None and times:
    return max(times) - start  # still running: up to its last logged iteration
  if len(times) > 1:
    return max(times) - min(times)
  return None


def _last(span: StageSpan, key: str) -> float | None:
  for r in reversed(span.records):
    v = _number(r.get(key))
    if v is not None:
      return v
  return None


def _stages_table(spans: Sequence[StageSpan]) -> list[str]:
  lines = ["| stage | status | env steps | iterations | last stand rate | best stand rate "
           "| last episode return | median steps/s | wall time |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
  for span in spans:
    sps = [v for v in (_number(r.get("steps_per_s")) for r in span.records
                       if r.get("phase") != "adaptation") if v is not None]
    ret = _last(span, "episode_return")
    lines.append(
        f"| {span.name} | {span.status} | {span.env_steps:,} | {len(span.records)} "
        f"| {_percent(_last(span, 'stand_rate'))} "
        f"| {_percent(_number(span.manifest.get('best_stand_rate')))} "
        f"| {'—' if ret is None else f'{ret:.3g}'} "
        f"| {'—' if not sps else f'{float(np.median(sps)):,.0f}'} "
        f"| {_duration_text(_stage_wall_time(span))} |")
  return lines


def _monitor_table(spans: Sequence[StageSpan]) -> list[str]:
  """The last monitor of every stage that has one: stand rate per start state."""
  names = monitor_scenarios(spans)
  last = []
  for span in spans:
    rows = [r for r in span.records if _monitor_rates(r) or
            _number(_monitor_mean(r)) is not None]
    if rows:
      last.append((span, rows[-1]))
  if not last:
    return []
  # The actor: the privileged one during PPO, the deployable one in the adaptation phase.
  lines = ["Last monitor of each stage:", "",
           "| stage | env steps | actor | mean | " + " | ".join(f"`{n}`" for n in names) + " |",
           "|---|---:|---|---:|" + "---:|" * len(names)]
  for span, r in last:
    rates = _monitor_rates(r)
    actor = r["monitor"].get("actor", "privileged") if isinstance(r.get("monitor"), dict) else "—"
    lines.append(f"| {span.name} | {int(r['env_steps']):,} | {actor} "
                 f"| {_percent(_number(_monitor_mean(r)))} | "
                 + " | ".join(_percent(_number(rates.get(n))) if n in rates else "—"
                              for n in names) + " |")
  return lines + [""]


def _cell_entry(cell: dict | None) -> str:
  if cell is None:
    return "—"
  rate = _number(cell.get("success_rate"))
  ci = cell.get("ci95") or []
  ours = _percent(rate)
  if len(ci) == 2 and _number(ci[0]) is not None and _number(ci[1]) is not None:
    ours += f" [{100 * ci[0]:.0f}–{100 * ci[1]:.0f}]"
  paper = _number(cell.get("paper_success_rate"))
  return ours + (f" · {_percent(paper)}" if paper is not None else "")


def _time_entry(cell: dict | None) -> str:
  if cell is None:
    return "—"
  m, s = _number(cell.get("recovery_time_mean")), _number(cell.get("recovery_time_std"))
  ours = "—" if m is None else f"{m:.2f} ± {s or 0.0:.2f} s"
  pt = cell.get("paper_recovery_time")
  if isinstance(pt, (list, tuple)) and len(pt) == 2 and _number(pt[0]) is not None:
    ours += f" · {pt[0]:.2f} ± {_number(pt[1]) or 0.0:.2f} s"
  return ours


def _experiment_tables(evals: Sequence[Evaluation], experiment: str) -> list[str]:
  xs, series, _ = experiment_layout(evals, experiment)
  header = "| | " + " | ".join(x.replace("\n", " ") for x in xs) + " |"
  rule = "|---|" + "---:|" * len(xs)
  lines = ["Success rate, ours [95% Wilson CI] · paper:", "", header, rule]
  for s in series:
    lines.append(f"| {s.label} | " + " | ".join(_cell_entry(s.cells.get(x)) for x in xs) + " |")
  lines += ["", "Recovery time, ours (mean ± std over successes) · paper:", "", header, rule]
  for s in series:
    lines.append(f"| {s.label} | " + " | ".join(_time_entry(s.cells.get(x)) for x in xs) + " |")
  return lines


def _eval_list(evals: Sequence[Evaluation], run: Path) -> list[str]:
  lines = ["| directory | protocol | backend | seed | trials per cell | cells | checkpoint "
           "| stage | env steps |", "|---|---|---|---:|---:|---:|---|---|---:|"]
  for e in evals:
    d = e.data
    steps = _number(d.get("env_steps"))
    lines.append(
        f"| `{_rel(e.directory, run)}` | {e.protocol} | {e.backend} | {d.get('seed', '—')} "
        f"| {d.get('trials', '—')} | {len(d['cells'])} | `{d.get('checkpoint', '—')}` "
        f"| {_stage_name(d.get('stage'))} | {'—' if steps is None else f'{int(steps):,}'} |")
  return lines


def _stage_name(stage: Any) -> str:
  if isinstance(stage, dict):
    return str(stage.get("name", "—"))
  return "—" if stage is None else str(stage)


# --------------------------------------------------------------------------------------------
# The report


def report(request: dict) -> dict:
  """Writes the plots and `report.md` of `request["run"]` into `request["out_dir"]`."""
  req = facade_requests.parse("report", facade_requests.ReportRequest, request)
  run = Path(req.run)
  out = Path(req.out_dir or run / "report")
  manifest = read_manifest(run)
  records, bad_lines = read_metrics(run / "metrics.jsonl")
  spans = stage_spans(manifest, records)
  evals, eval_notes = read_evaluations(run)
  out.mkdir(parents=True, exist_ok=True)

  def link(path: Path) -> str:  # relative to report.md, so the report directory can move
    return _rel(path, out)

  plots: list[Path] = []
  md: list[str] = [f"# Run report: {manifest.get('name', run.name)}", ""]
  md += _run_summary(run, manifest, spans, records)
  md += ["", "## Stages", ""] + _stages_table(spans)
  if bad_lines:
    md += ["", f"{bad_lines} line(s) of metrics.jsonl could not be read (a line being written "
           "while training, or a damaged file) and are left out."]

  md += ["", "## Training", ""]
  if not records:
    md += ["metrics.jsonl has no iterations yet: there are no training curves."]
  else:
    curves = out / "learning_curves.png"
    counts = plot_learning_curves(spans, curves)
    plots.append(curves)
    md += ["### Learning curves", "",
           "Episode return, stand rate (fraction of the episodes ended in an iteration that "
           "reached stable standing) and recovery time of every stage against the cumulative "
           "env steps; dashed lines mark stage boundaries, grey spans the RMA adaptation phase.",
           "", f"![learning curves]({link(curves)})", ""]
    for key, why in (("episode_return", "no episode ended"),
                     ("stand_rate", "no episode ended"),
                     ("recovery_time", "no episode reached stable standing")):
      if counts[key] == 0:
        md.append(f"- No {key.replace('_', ' ')} in any iteration (every value is null: {why}).")
    for span in spans:
      if len(span.records) == 1:
        md.append(f"- Stage {span.name} has a single iteration: its curves are one point.")
      elif not span.records and span.status not in ("pending",):
        md.append(f"- Stage {span.name} ({span.status}) has no metrics.")
    md += ["", "### Stand rate per start state", ""]
    if any(_monitor_rates(r) or _number(_monitor_mean(r)) is not None
           for span in spans for r in span.records):
      monitor = out / "monitor_stand_rate.png"
      plot_monitor(spans, monitor)
      plots.append(monitor)
      md += ["The deterministic monitor (`[stage.monitor]`: the policy's mean action, no "
             "action noise, a fixed number of episodes from each start state every few "
             "iterations): the fraction of episodes from each start state that reached stable "
             "standing, and their mean (dashed), against the cumulative env steps; dashed "
             "vertical lines mark stage boundaries. With key-state initialization it rises in "
             "steps as the policy learns to get up from each state in turn.", "",
             f"![stand rate per start state]({link(monitor)})", ""]
      md += _monitor_table(spans)
    else:
      md.append("No iteration of metrics.jsonl carries a `monitor` (the deterministic "
                "per-start-state check, `[stage.monitor] every > 0`): this plot is skipped.")
    standing = out / "standing_reward.png"
    drawn = plot_standing_reward(spans, standing)
    plots.append(standing)
    md += ["", "### Standing reward", "",
           "The standing term's mean weighted reward per control step (the paper's "
           "training-analysis curve: with key-state initialization it rises in steps as the "
           "agent learns to stand up from each key state).", "",
           f"![standing reward]({link(standing)})", ""]
    if drawn == 0:
      md.append("- No `standing` reward term was logged.")
    losses = out / "losses.png"
    loss_counts = plot_losses(spans, losses)
    plots.append(losses)
    md += ["", "### Losses", "", "PPO losses of every stage and the RMA adaptation module's "
           "latent regression loss.", "", f"![losses]({link(losses)})", ""]
    missing = [k for k, c in loss_counts.items() if c == 0]
    if missing:
      md.append(f"- Not logged: {', '.join(missing)}.")

  md += ["", "## Evaluations", ""]
  md += [f"- {n}" for n in eval_notes]
  if not evals:
    md += ["No evaluation yet (no `eval/*/eval.json` in the run): run `hifar eval "
           f"{run}` to measure it with the paper's protocols."]
  else:
    md += _eval_list(evals, run)
    for protocol in _unique(e.protocol for e in evals):
      group = [e for e in evals if e.protocol == protocol]
      backends = _unique(e.backend for e in group)
      md += ["", f"### Protocol {protocol}", ""]
      if len(backends) > 1:
        md += [f"Sim-to-sim: evaluated with {' and '.join(backends)}; each backend is one "
               "series.", ""]
      experiments = _unique(str(c.get("experiment")) for e in group for c in e.data["cells"]
                            if isinstance(c, dict))
      if not experiments:
        md += ["No cells in this protocol's evaluations."]
      for experiment in experiments:
        name = f"eval_{_slug(protocol)}_{_slug(experiment)}.png"
        path = out / name
        plot_experiment(group, protocol, experiment, path)
        plots.append(path)
        title = EXPERIMENTS.get(experiment, (experiment.replace("_", " "),))[0]
        md += [f"#### {title}", "", f"![{protocol} {experiment}]({link(path)})", ""]
        md += _experiment_tables(group, experiment) + [""]

  markdown = out / "report.md"
  text = "\n".join(md).rstrip() + "\n"
  write_atomic(markdown, text)
  return {"markdown": str(markdown), "plots": [str(p) for p in plots]}


def _slug(text: str) -> str:
  return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in text) or "_"


def _run_summary(run: Path, manifest: dict, spans: Sequence[StageSpan],
                 records: Sequence[dict]) -> list[str]:
  start, end = _timestamp(manifest.get("started_at")), _timestamp(manifest.get("ended_at"))
  if start is not None and end is None:
    times = [t for t in (_number(r.get("wall_time")) for r in records) if t is not None]
    end = max(times) if times else None
    wall = f"{_duration_text(None if end is None else end - start)} so far"
  else:
    wall = _duration_text(None if start is None or end is None else end - start)
  stand = None
  for span in reversed(spans):
    stand = _last(span, "stand_rate")
    if stand is not None:
      stand = f"{_percent(stand)} (stage {span.name}, last iteration that reported one)"
      break
  sessions = manifest.get("sessions") or []
  resumed = sum(1 for s in sessions if isinstance(s, dict) and s.get("resumed"))
  return [
      f"- Run directory: `{run}`",
      f"- Status: **{manifest.get('status', 'unknown')}**; stages: "
      + ", ".join(f"{s.name} ({s.status})" for s in spans),
      f"- Env steps: {sum(s.env_steps for s in spans):,} in all ("
      + ", ".join(f"{s.name} {_steps_text(s.env_steps)}" for s in spans) + ")",
      f"- Final stand rate: {stand or '— (no iteration reported one)'}",
      f"- Wall time: {wall}"
      + (f" over {len(sessions)} sessions ({resumed} resumed)" if len(sessions) > 1 else ""),
      f"- Seed {manifest.get('seed', '—')}, backend {manifest.get('backend', '—')}, "
      f"git {manifest.get('git_commit') or '—'}, started {manifest.get('started_at') or '—'}",
  ]
