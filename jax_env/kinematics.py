"""Cheap forward kinematics of the robot in JAX, independent of the physics backend.

Resets must place a sampled pose so that its lowest collision point sits just above the floor,
and must put the obstacle ball between the legs. Running the physics engine's own forward pass
for that would double the cost of a reset (and tie scenarios to one backend), so this module
re-derives body and geom poses from the model's constant tables: one pass down the (topologically
ordered) body tree with the free joint of the Trunk and one hinge per robot body.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jax_env import robot


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
  """Hamilton product of (w, x, y, z) quaternions."""
  aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
  bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
  return jnp.stack([
      aw * bw - ax * bx - ay * by - az * bz,
      aw * bx + ax * bw + ay * bz - az * by,
      aw * by - ax * bz + ay * bw + az * bx,
      aw * bz + ax * by - ay * bx + az * bw,
  ], axis=-1)


def quat_to_mat(q: jax.Array) -> jax.Array:
  """[..., 4] unit quaternions (w, x, y, z) to [..., 3, 3] rotation matrices."""
  q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  return jnp.stack([
      jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
      jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
      jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
  ], axis=-2)


def axis_angle_quat(axis, angle: jax.Array) -> jax.Array:
  """Quaternion of a rotation by `angle` [...] about the unit `axis` [3] or [..., 3]."""
  axis = jnp.asarray(axis, dtype=jnp.float32)
  half = 0.5 * angle
  return jnp.concatenate([jnp.cos(half)[..., None], jnp.sin(half)[..., None] * axis], -1)


def rotate_inverse(q: jax.Array, v: jax.Array) -> jax.Array:
  """R(q)ᵀ v: a world vector in the frame of orientation q."""
  return jnp.einsum("...ji,...j->...i", quat_to_mat(q), v)


class Kinematics:
  """Body and collision-geom poses of the robot for one qpos (vmap for a batch)."""

  def __init__(self, mj_model: mujoco.MjModel):
    m = mj_model
    self.body_ids = robot.body_ids(m)
    nb = int(self.body_ids.max()) + 1
    self.nbody = nb
    self.parent = np.asarray(m.body_parentid[:nb])
    self.body_pos = np.asarray(m.body_pos[:nb], np.float32)
    self.body_quat = np.asarray(m.body_quat[:nb], np.float32)
    self.root = int(self.body_ids[0])
    # One hinge (or nothing) per robot body below the root.
    self.hinge = {}
    for b in self.body_ids[1:]:
      n = int(m.body_jntnum[b])
      if n == 0:
        continue
      if n != 1:
        raise ValueError(f"body {m.body(b).name} has {n} joints; expected at most one hinge")
      j = int(m.body_jntadr[b])
      if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
        raise ValueError(f"joint {m.joint(j).name} is not a hinge")
      self.hinge[int(b)] = (int(m.jnt_qposadr[j]), np.asarray(m.jnt_axis[j], np.float32),
                            np.asarray(m.jnt_pos[j], np.float32))
    depth = {self.root: 0}
    for b in self.body_ids[1:]:
      depth[int(b)] = depth[int(self.parent[b])] + 1
    levels = [[int(b) for b in self.body_ids[1:] if depth[int(b)] == d]
              for d in range(1, max(depth.values()) + 1)]
    # Levels are padded to one width so that `bodies` can scan over them: the loop body is
    # traced and compiled once instead of once per level, which keeps this pass (run by every
    # reset, hence inside every environment step) cheap to compile. Padding rows write to a
    # scratch row `nbody` that is dropped at the end.
    width = max(len(lv) for lv in levels)

    def padded(values, fill):
      return np.array([list(v) + [fill] * (width - len(v)) for v in values])

    hinges = [[self.hinge.get(b) for b in lv] for lv in levels]
    self.levels = dict(
        ids=padded(levels, nb).astype(np.int32),
        parent=padded([[int(self.parent[b]) for b in lv] for lv in levels], 0).astype(np.int32),
        pos=padded([[self.body_pos[b] for b in lv] for lv in levels],
                   np.zeros(3)).astype(np.float32),
        quat=padded([[self.body_quat[b] for b in lv] for lv in levels],
                    np.array([1.0, 0.0, 0.0, 0.0])).astype(np.float32),
        hinge=padded([[h is not None for h in hs] for hs in hinges], False).astype(np.float32),
        qadr=padded([[h[0] if h else 0 for h in hs] for hs in hinges], 0).astype(np.int32),
        axis=padded([[h[1] if h else (0.0, 0.0, 1.0) for h in hs] for hs in hinges],
                    np.array([0.0, 0.0, 1.0])).astype(np.float32),
        anchor=padded([[h[2] if h else (0.0, 0.0, 0.0) for h in hs] for hs in hinges],
                      np.zeros(3)).astype(np.float32))
    robot_bodies = set(int(b) for b in self.body_ids)
    geoms = [g for g in range(m.ngeom) if int(m.geom_bodyid[g]) in robot_bodies
             and (m.geom_contype[g] or m.geom_conaffinity[g])]
    self.geom_ids = np.array(geoms, dtype=np.int32)
    self.geom_body = np.asarray(m.geom_bodyid[geoms])
    self.geom_type = np.asarray(m.geom_type[geoms])
    self.geom_size = np.asarray(m.geom_size[geoms], np.float32)
    self.geom_pos = np.asarray(m.geom_pos[geoms], np.float32)
    self.geom_quat = np.asarray(m.geom_quat[geoms], np.float32)
    supported = {int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                 int(mujoco.mjtGeom.mjGEOM_BOX)}
    for g, t in zip(geoms, self.geom_type):
      if int(t) not in supported:
        raise ValueError(f"geom {m.geom(g).name}: lowest-point estimate supports spheres, "
                         "capsules and boxes only")

  def bodies(self, qpos: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World positions [nbody, 3] and orientations [nbody, 4] (rows of non-robot bodies 0).

    Bodies are processed one tree level at a time (7 levels for the T1), each level as one
    vectorised gather/compute/scatter inside a `lax.scan` over the levels.
    """
    pos = jnp.zeros((self.nbody + 1, 3), qpos.dtype).at[self.root].set(qpos[0:3])
    quat = jnp.zeros((self.nbody + 1, 4), qpos.dtype).at[:, 0].set(1.0)
    quat = quat.at[self.root].set(qpos[3:7] / jnp.linalg.norm(qpos[3:7]))

    def level(carry, lv):
      pos, quat = carry
      ids, par = lv["ids"], lv["parent"]
      pq = quat[par]
      xq = quat_mul(pq, lv["quat"])
      xp = pos[par] + jnp.einsum("bij,bj->bi", quat_to_mat(pq), lv["pos"])
      angle = qpos[lv["qadr"]] * lv["hinge"]  # 0 for bodies without a hinge
      rot = quat_mul(xq, axis_angle_quat(lv["axis"], angle))
      # Rotation about the joint anchor: the anchor stays where it was.
      xp = xp + jnp.einsum("bij,bj->bi", quat_to_mat(xq) - quat_to_mat(rot), lv["anchor"])
      return (pos.at[ids].set(xp), quat.at[ids].set(rot)), None

    levels = jax.tree_util.tree_map(jnp.asarray, self.levels)
    (pos, quat), _ = jax.lax.scan(level, (pos, quat), levels)
    return pos[:self.nbody], quat[:self.nbody]

  def geoms(self, qpos: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World centres [ngeom_robot, 3] and rotation matrices [ngeom_robot, 3, 3]."""
    return self._geoms(*self.bodies(qpos))

  def _geoms(self, bpos, bquat):
    rb = quat_to_mat(bquat[self.geom_body])
    centre = bpos[self.geom_body] + jnp.einsum("gij,gj->gi", rb, self.geom_pos)
    rg = rb @ quat_to_mat(jnp.asarray(self.geom_quat))
    return centre, rg

  def lowest_point(self, qpos: jax.Array) -> jax.Array:
    """Lowest world z of any robot collision geom (exact for spheres, capsules, boxes)."""
    return self.lowest_point_of(*self.bodies(qpos))

  def lowest_point_of(self, bpos: jax.Array, bquat: jax.Array) -> jax.Array:
    """`lowest_point` from body poses already computed by `bodies`."""
    return jnp.min(self.geom_lowest_of(bpos, bquat))

  def geom_lowest(self, qpos: jax.Array) -> jax.Array:
    """Lowest world z of each robot collision geom [ngeom_robot] (order of `geom_ids`)."""
    return self.geom_lowest_of(*self.bodies(qpos))

  def geom_lowest_of(self, bpos: jax.Array, bquat: jax.Array) -> jax.Array:
    centre, rot = self._geoms(bpos, bquat)
    size = jnp.asarray(self.geom_size)
    cz = centre[:, 2]
    zrow = rot[:, 2, :]  # world z component of each geom axis
    sphere = cz - size[:, 0]
    capsule = cz - jnp.abs(zrow[:, 2]) * size[:, 1] - size[:, 0]
    box = cz - jnp.sum(jnp.abs(zrow) * size, axis=-1)
    t = jnp.asarray(self.geom_type)
    return jnp.where(t == int(mujoco.mjtGeom.mjGEOM_SPHERE), sphere,
                     jnp.where(t == int(mujoco.mjtGeom.mjGEOM_CAPSULE), capsule, box))
