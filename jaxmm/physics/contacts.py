"""Rectangular foot contacts as corner points on flat ground (normal +z): friction cone
(eq. 12, 19) and relaxed complementarity (eq. 20, 21)."""

import jax.numpy as jnp


def friction_cone(forces, friction_coefficient):
    """Linearised friction cone A f ≤ 0 (eq. 12, 19), 4 rows per corner.

    forces: (nc, 3) [N]. Returns (4 nc,): per corner f_x − μ f_z, −f_x − μ f_z, f_y − μ f_z,
    −f_y − μ f_z; feasible when every entry is ≤ 0.
    """
    tangential = forces[:, :2]
    normal = friction_coefficient * forces[:, 2:3]
    return jnp.stack(
        [tangential[:, 0:1] - normal, -tangential[:, 0:1] - normal, tangential[:, 1:2] - normal, -tangential[:, 1:2] - normal],
        axis=1,
    ).reshape(-1)


def normal_complementarity(forces, points, slack):
    """Relaxed normal complementarity d(c) n·f ≤ ε_n (eq. 20): f_z c_z − ε_n ≤ 0, (nc,).

    forces, points: (nc, 3); slack ε_n: (nc,).
    """
    return forces[:, 2] * points[:, 2] - slack


def planar_complementarity(forces, points, next_points, slack):
    """Relaxed planar complementarity (eq. 21): |f_z (c_xy[k+1] − c_xy[k])| ≤ ε_t, element-wise.

    forces, points: knot k, (nc, 3); next_points: knot k+1, (nc, 3); slack ε_t: (nc,).
    Returns (upper (2 nc,) ≤ 0, lower (2 nc,) ≥ 0) = (f_z Δc − ε_t, f_z Δc + ε_t), corner-major.
    """
    sliding = forces[:, 2:3] * (next_points[:, :2] - points[:, :2])
    return (sliding - slack[:, None]).reshape(-1), (sliding + slack[:, None]).reshape(-1)
