"""The whole-body dynamics a centroidal plan implies: joint torques from inverse dynamics with
the contact forces and the jets' thrust forces (eq. 5) as external forces."""

import jax.numpy as jnp

from jaxmm.physics.jets import thrust_forces
from jaxmm.rigid_body.centroidal import com_position
from jaxmm.rigid_body.dynamics import inverse_dynamics
from jaxmm.rigid_body.kinematics import frame_poses


def generalised_forces(robot, q, nu, nu_dot, contact_forces, thrust, gravity):
    """τ (6 + n,) that the motion (q, ν, ν̇) needs under the contact forces (nc, 3) [N] at the
    robot's contact corners, the thrusts T (nj,) [N] of its jets (F_j = −T_j R_j e_z, eq. 5) and
    gravity (3,) [m/s²] (``rigid_body.dynamics.inverse_dynamics``): the base force [N] and the base
    torque about the CoM [N m], world-aligned, then the joint torques [N m]. The base wrench is
    what the external forces leave unbalanced: zero under the full dynamics."""
    model = robot.model
    _, jet_rotations = frame_poses(model, q, robot.jet_frames)
    forces = jnp.concatenate([contact_forces, thrust_forces(thrust, jet_rotations)])
    tau = inverse_dynamics(model, q, nu, nu_dot, forces, robot.contact_frames + robot.jet_frames, gravity)
    lever = q[:3] - com_position(model, q)  # from the CoM to the base origin
    return jnp.concatenate([tau[:3], tau[3:6] + jnp.cross(lever, tau[:3]), tau[6:]])
