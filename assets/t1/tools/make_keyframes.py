"""Designs, settles, checks and writes the T1 keyframes into assets/t1/scene.xml.

Usage (from the repository root):
  python assets/t1/tools/make_keyframes.py            # design + settle + check + write
  python assets/t1/tools/make_keyframes.py --check    # only check the committed keys
  python assets/t1/tools/make_keyframes.py --draw DIR # also draw side / front views (PNG)

Each key state is a hand-designed posture (joint targets plus a base orientation) from a
classic scripted get-up: from the back (supine) the robot bends its knees, sits up on its
hands, then rolls forward into a crouch over its feet; from the front (prone) it sets its
hands under the shoulders, pushes up onto hands and knees, then brings the feet under the
hips into a crouch with the hands still down. For every posture the script

  1. places the joints and the base orientation, and lifts the base so that the lowest
     collision geom just touches the floor;
  2. lets it settle for SETTLE_S under PD (ctrl = the designed joint targets), so that
     contacts, joint sag and the base pose are physically consistent and at rest;
  3. takes the settled configuration as the key (qvel = 0, ctrl = its joint positions),
     moves the base back over the origin, and lifts it by any floor penetration deeper
     than 0.5 mm;
  4. checks it: no contact deeper than 1 mm, and holding it under PD (ctrl = key joints)
     for 1 s moves the Trunk origin by less than 5 cm.

The numbers written into scene.xml are the result; the committed XML holds them, so the
model never depends on this script at run time.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from pathlib import Path

import mujoco
import numpy as np

from jax_env import robot
from jax_env.robot import JOINT_NAMES

SCENE = Path(__file__).resolve().parents[1] / "scene.xml"
SETTLE_S = 2.0
HOLD_S = 1.0
MAX_PENETRATION = 1e-3
MAX_DRIFT = 0.05

JOINTS = JOINT_NAMES


@dataclasses.dataclass(frozen=True)
class Posture:
  """A posture: arm and leg values written for the LEFT side, base pitch (rad).

  The right side mirrors the left (roll and yaw joints change sign) unless `arm_right` /
  `leg_right` give it its own values, still written in left-side convention.
  """

  pitch: float  # base (Trunk) pitch about world y; -pi/2 = on the back, +pi/2 = face down
  arm: tuple[float, float, float, float]  # shoulder pitch, shoulder roll, elbow pitch, elbow yaw
  leg: tuple[float, float, float, float, float, float]  # hip p, r, y, knee, ankle p, r
  arm_right: tuple[float, float, float, float] | None = None
  leg_right: tuple[float, float, float, float, float, float] | None = None
  head: tuple[float, float] = (0.0, 0.0)
  settle: bool = True

  def joints(self) -> np.ndarray:
    q = _left_side(self.head, self.arm, self.leg)
    right = robot.mirror_left_to_right(
        _left_side(self.head, self.arm_right or self.arm, self.leg_right or self.leg))
    q[robot.RIGHT_JOINTS] = right[robot.RIGHT_JOINTS]
    return q


ARM_JOINTS = ("Shoulder_Pitch", "Shoulder_Roll", "Elbow_Pitch", "Elbow_Yaw")
LEG_JOINTS = ("Hip_Pitch", "Hip_Roll", "Hip_Yaw", "Knee_Pitch", "Ankle_Pitch", "Ankle_Roll")


def _left_side(head, arm, leg) -> np.ndarray:
  """[23] joints: the head's and the left arm's and leg's values, zeros elsewhere."""
  q = np.zeros(len(JOINT_NAMES))
  values = dict(zip(("AAHead_yaw", "Head_pitch"), head))
  values |= {f"Left_{j}": v for j, v in zip(ARM_JOINTS, arm)}
  values |= {f"Left_{j}": v for j, v in zip(LEG_JOINTS, leg)}
  for name, v in values.items():
    q[JOINT_NAMES.index(name)] = v
  return q


HOME_ARM = (0.0, -1.4, 0.0, -0.4)
HOME_LEG = (-0.2, 0.0, 0.0, 0.4, -0.2, 0.0)

POSTURES: dict[str, Posture] = {
    # Target standing state (paper Fig. 3B): the "home" pose, knees slightly bent, feet flat.
    "stand": Posture(pitch=0.0, arm=HOME_ARM, leg=HOME_LEG, settle=False),
    # Prone 1: lying face down, hands set beside the chest, elbows bent (push-up start).
    "ksi_prone_1": Posture(pitch=math.pi / 2, arm=(0.5, -1.4, 0.0, -2.3),
                           leg=(0.0, 0.0, 0.0, 0.1, 0.3, 0.0)),
    # Prone 2: pushed up on straight arms and knees (hands and knees).
    "ksi_prone_2": Posture(pitch=1.35, arm=(-1.5, -1.4, 0.0, 0.0),
                           leg=(-1.35, 0.0, 0.0, 1.9, 0.35, 0.0)),
    # Prone 3: crouched back on knees and toes, hips low over the heels, trunk leaning
    # forward, hands on the floor in front of the knees: the last phase before the feet
    # come under the hips. (With T1's hip flexion limit of -1.8 the hands cannot reach the
    # floor once the feet are under the hips, so the prone crouch is taken on the knees.)
    "ksi_prone_3": Posture(pitch=0.8, arm=(-1.3, -1.4, 0.0, 0.0),
                           leg=(-1.6, 0.0, 0.0, 2.3, 0.2, 0.0)),
    # Supine 1: lying on the back, knees bent with the feet flat, arms along the body.
    "ksi_supine_1": Posture(pitch=-math.pi / 2, arm=(0.2, -1.4, 0.0, 0.0),
                            leg=(-0.9, 0.0, 0.0, 2.1, 0.35, 0.0)),
    # Supine 2: sitting up, leaning back on the hands placed behind the hips.
    "ksi_supine_2": Posture(pitch=-0.6, arm=(0.9, -1.4, 0.0, 0.0),
                            leg=(-1.3, 0.0, 0.0, 2.2, -0.3, 0.0)),
    # Supine 3: rolled forward into a deep crouch over flat feet, arms reaching forward.
    "ksi_supine_3": Posture(pitch=0.25, arm=(-1.2, -1.4, 0.0, -0.3),
                            leg=(-1.7, 0.0, 0.0, 2.3, -0.85, 0.0)),
}


def _robot_geoms(model) -> list[int]:
  floor = model.geom("floor").id
  obstacle = model.geom("obstacle").id
  return [g for g in range(model.ngeom) if g not in (floor, obstacle)
          and model.geom_contype[g] | model.geom_conaffinity[g]]


def lowest_point(model, data) -> float:
  """Lowest z over the robot's collision geoms (spheres, capsules, boxes)."""
  low = np.inf
  for g in _robot_geoms(model):
    pos, mat, size = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
    t = model.geom_type[g]
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
      z = pos[2] - size[0]
    elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
      axis = mat[:, 2] * size[1]
      z = min(pos[2] + axis[2], pos[2] - axis[2]) - size[0]
    elif t == mujoco.mjtGeom.mjGEOM_BOX:
      corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
      z = (pos + (corners * size) @ mat.T)[:, 2].min()
    else:
      raise ValueError(f"unexpected geom type {t} for geom {model.geom(g).name}")
    low = min(low, z)
  return float(low)


def place(model, posture: Posture) -> np.ndarray:
  """qpos with the designed joints and base pitch, lowest geom touching the floor."""
  data = mujoco.MjData(model)
  data.qpos[7:] = np.clip(posture.joints(), model.jnt_range[1:, 0], model.jnt_range[1:, 1])
  data.qpos[3:7] = [math.cos(posture.pitch / 2), 0.0, math.sin(posture.pitch / 2), 0.0]
  data.qpos[2] = 1.0
  mujoco.mj_kinematics(model, data)
  data.qpos[2] -= lowest_point(model, data)
  return data.qpos.copy()


def min_contact_dist(model, qpos) -> float:
  data = mujoco.MjData(model)
  data.qpos[:] = qpos
  mujoco.mj_forward(model, data)
  return float(min((data.contact.dist[i] for i in range(data.ncon)), default=np.inf))


def simulate(model, qpos, ctrl, seconds) -> np.ndarray:
  data = mujoco.MjData(model)
  data.qpos[:] = qpos
  data.ctrl[:] = ctrl
  for _ in range(int(round(seconds / model.opt.timestep))):
    mujoco.mj_step(model, data)
  return data.qpos.copy(), data.qvel.copy()


def hold_drift(model, qpos, seconds=HOLD_S) -> float:
  """How far the Trunk origin moves while PD holds the key's own joint positions."""
  end, _ = simulate(model, qpos, qpos[7:], seconds)
  return float(np.linalg.norm(end[:3] - qpos[:3]))


def symmetrize(qpos: np.ndarray) -> np.ndarray:
  """Averages a configuration with its left-right mirror image (removes settle noise)."""
  from jax_env import robot  # pylint: disable=import-outside-toplevel
  sym = 0.5 * (qpos + robot.mirror_qpos(qpos))
  sym[3:7] /= np.linalg.norm(sym[3:7])
  return sym


def design(model, name: str) -> np.ndarray:
  posture = POSTURES[name]
  qpos = place(model, posture)
  if posture.settle:
    qpos, _ = simulate(model, qpos, qpos[7:], SETTLE_S)
    qpos[0:2] = 0.0
    if posture.arm_right is None and posture.leg_right is None:
      qpos = symmetrize(qpos)
    # Joint limits are soft: settled joints may sit a hair outside their range.
    qpos[7:] = np.clip(qpos[7:], model.jnt_range[1:, 0], model.jnt_range[1:, 1])
  qpos[3:7] /= np.linalg.norm(qpos[3:7])
  # Lift the base out of any penetration deeper than 0.8 mm (settled contacts sit a
  # fraction of a millimetre deep; lifting more would leave the other contacts hanging).
  dist = min_contact_dist(model, qpos)
  if dist < -8e-4:
    qpos[2] += -dist - 8e-4
  return qpos


def check(model, name, qpos) -> tuple[float, float]:
  dist = min_contact_dist(model, qpos)
  drift = hold_drift(model, qpos)
  return dist, drift


def keys_xml(keys: dict[str, np.ndarray]) -> str:
  fmt = lambda v: " ".join(f"{x:.6g}" if abs(x) > 5e-7 else "0" for x in v)
  lines = ["  <keyframe>"]
  for name, qpos in keys.items():
    lines.append(f'    <key name="{name}"')
    lines.append(f'         qpos="{fmt(qpos[:7])}')
    lines.append(f'               {fmt(qpos[7:])}"')
    lines.append(f'         ctrl="{fmt(qpos[7:])}"/>')
  lines.append("  </keyframe>")
  return "\n".join(lines)


def write_keys(keys: dict[str, np.ndarray]) -> None:
  text = SCENE.read_text()
  block = "  <!-- KEYFRAMES BEGIN -->\n" + keys_xml(keys) + "\n  <!-- KEYFRAMES END -->"
  new, n = re.subn(r"  <!-- KEYFRAMES BEGIN -->.*?<!-- KEYFRAMES END -->", block, text,
                   flags=re.S)
  if n != 1:
    raise RuntimeError(f"{SCENE}: KEYFRAMES markers not found")
  SCENE.write_text(new)


def draw(model, qpos, path: Path) -> None:
  """Side (x-z) and front (y-z) silhouettes of the collision geoms, for eyeballing."""
  from PIL import Image, ImageDraw  # pylint: disable=import-outside-toplevel
  data = mujoco.MjData(model)
  data.qpos[:] = qpos
  mujoco.mj_forward(model, data)
  scale, w, h = 300, 900, 450
  img = Image.new("RGB", (w, h), "white")
  dr = ImageDraw.Draw(img)
  for panel, (ax, x0) in enumerate(((0, 225), (1, 675))):
    to_px = lambda p: (x0 + p[ax] * scale, h - 30 - p[2] * scale)
    dr.line([(x0 - 220, h - 30), (x0 + 220, h - 30)], fill="black")
    for g in _robot_geoms(model):
      pos, mat, size = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
      t = model.geom_type[g]
      col = ((37 * g) % 200, 90, 220 - (23 * g) % 180)
      if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        cx, cy = to_px(pos)
        r = size[0] * scale
        dr.ellipse([cx - r, cy - r, cx + r, cy + r], outline=col, width=2)
      elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        a, b = pos + mat[:, 2] * size[1], pos - mat[:, 2] * size[1]
        dr.line([to_px(a), to_px(b)], fill=col, width=int(2 * size[0] * scale))
      else:
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        pts = [to_px(p) for p in pos + (corners * size) @ mat.T]
        for i in range(8):
          for j in range(i + 1, 8):
            if bin(i ^ j).count("1") == 1:
              dr.line([pts[i], pts[j]], fill=col, width=2)
  img.save(path)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--check", action="store_true", help="only check the committed keys")
  parser.add_argument("--only", nargs="*", help="design only these keys (others kept)")
  parser.add_argument("--draw", type=Path, help="directory for PNG views of each key")
  args = parser.parse_args(argv)

  model = mujoco.MjModel.from_xml_path(str(SCENE))
  committed = {model.key(i).name: model.key(i).qpos.copy() for i in range(model.nkey)}
  if args.check:
    keys = committed
  else:
    keys = {}
    for name in POSTURES:
      if args.only and name not in args.only and name in committed:
        keys[name] = committed[name]
      else:
        keys[name] = design(model, name)
  ok = True
  for name, qpos in keys.items():
    dist, drift = check(model, name, qpos)
    good = dist >= -MAX_PENETRATION and drift < MAX_DRIFT
    ok &= good
    print(f"{name:14s} z={qpos[2]:.4f}  min contact dist={dist * 1e3:+.2f} mm  "
          f"1 s PD-hold drift={drift * 100:.2f} cm  {'ok' if good else 'FAIL'}")
    if args.draw:
      args.draw.mkdir(parents=True, exist_ok=True)
      draw(model, qpos, args.draw / f"{name}.png")
  if not args.check:
    write_keys(keys)
    print(f"wrote {len(keys)} keyframes to {SCENE}")
  return 0 if ok else 1


if __name__ == "__main__":
  sys.exit(main())
