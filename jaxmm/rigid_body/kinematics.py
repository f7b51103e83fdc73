"""Forward kinematics of bodies and frames, and frame Jacobians (world-aligned, "mixed")."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3
from jaxmm.rigid_body.configuration import check_configuration


def joint_positions_all(model, q):
    """Positions of every moving joint (optimised from q, locked from the model): (nb − 1,)."""
    topology = model.topology
    nj = len(topology.joint_names)
    values = jnp.zeros(nj, dtype=q.dtype)
    values = values.at[np.asarray(topology.optimised_joints, int)].set(q[7:])
    return values.at[np.asarray(topology.locked_joints, int)].set(model.locked_positions)


def _axis_rotation(axis, angle):
    """Rotation by angle about a unit axis (Rodrigues): (3,), () → (3, 3)."""
    S = so3.skew(axis)
    return jnp.eye(3) + jnp.sin(angle) * S + (1 - jnp.cos(angle)) * (S @ S)


def body_poses(model, q):
    """World poses of all bodies.

    q: (7 + n,) configuration. Returns rotations (nb, 3, 3) and positions (nb, 3) [m].
    The tree is walked one depth level at a time, so the traced graph grows with the depth
    of the tree, not with its number of links. Each level is one batched product of 3 × 4
    placements [R | p] (child = parent ∘ joint: R_c = R_p R_j, p_c = p_p + R_p p_j), its
    parents gathered from the level before alone: one product and one gather per level, with
    no growing array to copy (and fewer operations for the derivatives to transpose).
    """
    q = check_configuration(model, q)
    topology = model.topology
    angles = joint_positions_all(model, q)
    prismatic = np.asarray(topology.joint_is_prismatic, bool)
    revolute_angles = jnp.where(prismatic, 0.0, angles)
    motion = jax.vmap(_axis_rotation)(model.joint_axis, revolute_angles)
    slide = jnp.where(prismatic, angles, 0.0)[:, None] * model.joint_axis
    local_p = model.joint_translation + jnp.einsum("jab,jb->ja", model.joint_rotation, slide)
    local = jnp.concatenate([model.joint_rotation @ motion, local_p[..., None]], axis=2)  # (nb − 1, 3, 4)

    # Bodies are numbered by depth: each level is a contiguous range whose parents are the
    # previous level's bodies.
    parent = np.asarray(topology.body_parent)
    level = jnp.concatenate([so3.quaternion_to_rotation(q[3:7]), q[:3, None]], axis=1)[None]
    levels, offset = [level], 0
    for start, stop in topology.body_levels:
        up = level[parent[start:stop] - offset]
        level = up[..., :3] @ local[start - 1 : stop - 1] + jnp.pad(up[..., 3:], ((0, 0), (0, 0), (3, 0)))
        levels.append(level)
        offset = start
    placements = jnp.concatenate(levels)
    return placements[..., :3], placements[..., 3]


def frame_poses(model, q, frames=None):
    """World poses of frames.

    frames: names or indices (resolved in Python, so they must be static), or None for all.
    Returns positions (k, 3) [m] and rotations (k, 3, 3) (frame to world).
    """
    indices = np.arange(len(model.frame_names)) if frames is None else np.asarray(
        model.frame_indices(frames), int
    )
    R_body, p_body = body_poses(model, q)
    bodies = np.asarray(model.topology.frame_body, int)[indices]
    R_b, p_b = R_body[bodies], p_body[bodies]
    positions = p_b + jnp.einsum("fij,fj->fi", R_b, model.frame_translation[indices])
    rotations = R_b @ model.frame_rotation[indices]
    return positions, rotations


def frame_pose(model, q, frame):
    """World pose of one frame (name or index): position (3,) [m], rotation (3, 3)."""
    positions, rotations = frame_poses(model, q, (frame,))
    return positions[0], rotations[0]


def frame_jacobian(model, q, frame):
    """Jacobian of one frame in mixed velocity: (6, 6 + n), rows [linear; angular].

    Maps ν to (velocity of the frame origin, angular velocity of the frame), both in the
    world frame, so [v; ω] = J(q) ν.
    """
    index = model.frame_index(frame)
    R_body, p_body = body_poses(model, q)
    body = model.topology.frame_body[index]
    position = p_body[body] + R_body[body] @ model.frame_translation[index]
    axes, origins = joint_axes_world(model, R_body, p_body)
    moves = model.topology.joint_support[:, body]
    prismatic = np.asarray(model.topology.joint_is_prismatic, bool)
    linear = jnp.where(prismatic[:, None], axes, jnp.cross(axes, position - origins))
    angular = jnp.where(prismatic[:, None], 0.0, axes)
    joints_part = jnp.where(moves[:, None], jnp.concatenate([linear, angular], axis=1), 0.0)
    base = jnp.block(
        [[jnp.eye(3), -so3.skew(position - q[:3])], [jnp.zeros((3, 3)), jnp.eye(3)]]
    )
    optimised = np.asarray(model.topology.optimised_joints, int)
    return jnp.concatenate([base, joints_part[optimised].T], axis=1)


def joint_axes_world(model, R_body, p_body):
    """World axis (nb − 1, 3) and origin (nb − 1, 3) of each moving joint."""
    axes = jnp.einsum("jab,jb->ja", R_body[1:], model.joint_axis)
    return axes, p_body[1:]
