"""The paper's simulation protocols as data: one `Cell` per (experiment, scenario, setting), with
the paper's own numbers beside it (hifar.tex, "Simulation Experiments").

Every experiment starts from the standard setup (supine or prone, torso 11.7 kg, friction 1.0, no
disturbance; conditions.evaluation_stage) and changes one thing:

| experiment     | paper table                         | settings                              |
|----------------|-------------------------------------|---------------------------------------|
| standard       | sim: 100 % both; real robot: time   | —                                     |
| planar_push    | "Planar Force Experiments"          | 50–300 N, forward (prone) / backward  |
|                |                                     | (supine) along the torso, 0.8 s after |
|                |                                     | the recovery starts, for 200 ms       |
| lateral_push   | "Lateral Force Experiments"         | 50–250 N leftward along the torso     |
| load           | "Load Experiments"                  | +2.4, +5.9, +9.4, +11.7 kg on the torso|
| friction       | "Friction Experiments"              | 0.8, 0.6, 0.4, 0.2, 0.1               |
| torque_limit   | "Torque Limit Experiments"          | 85 %, 75 % of the actuator limits     |
| random_initial | real robot, qualitative             | lateral, sitting, crossed legs, drop  |
| terrain        | real robot, qualitative             | slope, obstacle between the legs      |
| keystate       | — (our diagnostic)                  | stand, the six KSI key states, supine,|
|                |                                     | prone: one cell per start state       |

The paper's recovery times (2.711 ± 0.319 s supine, 2.875 ± 0.474 s prone) come from its
real-robot table, the only recovery times it reports; its random-initial-state and terrain
experiments were run on the real robot and reported without numbers, so those cells carry none.

The `keystate` protocol is not the paper's: it measures, under the same nominal setup, how well
the policy gets up (or stays up) from each start state of its key-state curriculum — the
`stand` keyframe, the six key states of KSI, and lying supine and prone — so a stage whose
training stand rate hides a start state it never learned shows it cell by cell.
"""

from __future__ import annotations

import dataclasses

from jax_env.evaluation.conditions import Condition, planar_direction

EXPERIMENTS: tuple[str, ...] = ("standard", "planar_push", "lateral_push", "load", "friction",
                                "torque_limit", "random_initial", "terrain", "keystate")
PROTOCOLS: tuple[str, ...] = ("paper", "quick", "keystate")
DEFAULT_TRIALS = {"paper": 100, "quick": 8, "keystate": 8}
# The paper's tables list prone first.
LYING = ("prone", "supine")

# Paper values (hifar.tex).
PUSH_START_S = 0.8
PUSH_DURATION_S = 0.2
PLANAR_FORCES = (50.0, 100.0, 150.0, 200.0, 250.0, 300.0)
LATERAL_FORCES = (50.0, 100.0, 150.0, 200.0, 250.0)
EXTRA_TORSO_MASS = (2.4, 5.9, 9.4, 11.7)
FRICTIONS = (0.8, 0.6, 0.4, 0.2, 0.1)
TORQUE_LIMITS = (0.85, 0.75)
RANDOM_INITIAL = ("lateral", "sitting", "crossed_legs", "random_drop")
TERRAIN_CELLS = ("slope", "obstacle")
# The keystate protocol's start states: standing, the key states of KSI, the lying poses.
KEYSTATE_CELLS = ("stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1",
                  "ksi_supine_2", "ksi_supine_3", "supine", "prone")

PAPER_SUCCESS = {
    ("standard", "prone"): (1.0,), ("standard", "supine"): (1.0,),
    ("planar_push", "prone"): (1.0, 1.0, 1.0, 1.0, 0.8, 0.0),
    ("planar_push", "supine"): (1.0, 1.0, 1.0, 1.0, 1.0, 0.6),
    ("lateral_push", "prone"): (1.0, 1.0, 1.0, 0.9, 0.1),
    ("lateral_push", "supine"): (1.0, 1.0, 1.0, 1.0, 0.0),
    ("load", "prone"): (1.0, 1.0, 1.0, 1.0),
    ("load", "supine"): (1.0, 1.0, 1.0, 0.0),
    ("friction", "prone"): (1.0, 1.0, 1.0, 0.9, 0.0),
    ("friction", "supine"): (1.0, 1.0, 1.0, 1.0, 0.9),
    ("torque_limit", "prone"): (1.0, 1.0),
    ("torque_limit", "supine"): (1.0, 0.6),
}
PAPER_RECOVERY_TIME = {"supine": (2.711, 0.319), "prone": (2.875, 0.474)}


@dataclasses.dataclass(frozen=True)
class Cell:
  """One protocol cell: a condition, its labels, and the paper's numbers where it has them."""

  experiment: str
  setting: str  # column label, e.g. "150N"
  value: float | None  # the setting as a number (N, kg, μ, fraction), None where it has none
  condition: Condition
  paper_success_rate: float | None = None
  paper_recovery_time: tuple[float, float] | None = None

  @property
  def scenario(self) -> str:
    return self.condition.scenario

  @property
  def label(self) -> str:
    return f"{self.experiment}/{self.scenario}/{self.setting}"


def table_row(experiment: str, scenario: str) -> str:
  """The row of eval.md's table a cell appears in (the paper's rows are prone / supine)."""
  return "initial state" if experiment == "random_initial" else scenario


def _num(x: float) -> str:
  return f"{x:g}"


def _lying_cells(experiment: str, values, setting, condition) -> list[Cell]:
  cells = []
  for scenario in LYING:
    paper = PAPER_SUCCESS[(experiment, scenario)]
    for value, rate in zip(values, paper, strict=True):
      cells.append(Cell(experiment, setting(value), value, condition(scenario, value), rate))
  return cells


def _push(direction):
  def make(scenario, force):
    return Condition(scenario=scenario, push_force=force,
                     push_direction=direction or planar_direction(scenario),
                     push_start_s=PUSH_START_S, push_duration_s=PUSH_DURATION_S)
  return make


def paper_cells() -> list[Cell]:
  """Every cell of the paper's simulation experiments, plus the random initial states and the
  terrains of its real-robot experiments."""
  cells = [Cell("standard", "standard", None, Condition(scenario=s),
                PAPER_SUCCESS[("standard", s)][0], PAPER_RECOVERY_TIME[s]) for s in LYING]
  cells += _lying_cells("planar_push", PLANAR_FORCES, lambda f: f"{_num(f)}N", _push(None))
  cells += _lying_cells("lateral_push", LATERAL_FORCES, lambda f: f"{_num(f)}N", _push("left"))
  cells += _lying_cells("load", EXTRA_TORSO_MASS, lambda m: f"+{_num(m)}kg",
                        lambda s, m: Condition(scenario=s, extra_torso_mass=m))
  cells += _lying_cells("friction", FRICTIONS, _num,
                        lambda s, mu: Condition(scenario=s, friction=mu))
  cells += _lying_cells("torque_limit", TORQUE_LIMITS, lambda t: f"{round(100 * t)}%",
                        lambda s, t: Condition(scenario=s, torque_limit=t))
  cells += [Cell("random_initial", s, None, Condition(scenario=s)) for s in RANDOM_INITIAL]
  cells += [Cell("terrain", t, None, Condition(scenario=s, terrain=t))
            for s in LYING for t in TERRAIN_CELLS]
  return cells


# The quick protocol: the standard cells and one informative cell of every other experiment
# (the setting where the paper's policy starts to fail, or the hardest it still passes).
_QUICK = ("standard/prone/standard", "standard/supine/standard", "planar_push/prone/250N",
          "lateral_push/supine/200N", "load/supine/+9.4kg", "friction/prone/0.2",
          "torque_limit/supine/75%", "random_initial/sitting/sitting",
          "terrain/prone/obstacle")


def quick_cells() -> list[Cell]:
  by_label = {c.label: c for c in paper_cells()}
  return [by_label[label] for label in _QUICK]


def keystate_cells() -> list[Cell]:
  """One cell per start state of the key-state curriculum, each under the nominal setup (no
  push, nominal mass and friction, no randomization); the paper reports none of them."""
  return [Cell("keystate", s, None, Condition(scenario=s)) for s in KEYSTATE_CELLS]


def cells(protocol: str) -> list[Cell]:
  if protocol == "paper":
    return paper_cells()
  if protocol == "quick":
    return quick_cells()
  if protocol == "keystate":
    return keystate_cells()
  raise ValueError(f"unknown protocol {protocol!r}; valid: {', '.join(PROTOCOLS)}")
