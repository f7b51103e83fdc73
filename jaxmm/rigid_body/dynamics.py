"""Inverse dynamics (the recursive Newton–Euler algorithm), the mass matrix and the bias forces,
for the mixed velocity ν = (ṗ, ω, ṡ) of ``model``.

Every spatial quantity is written in ground coordinates (Featherstone, "Rigid Body Dynamics
Algorithms", 2008, §2.9 and §5.3): a motion (ω, v_O) or a force (n_O, f) is expressed in the
world frame at the world origin O. Then no transform is needed between a body and its parent:
the forward recursion v_i = v_λ(i) + S_i ṡ_i, a_i = a_λ(i) + S_i s̈_i + v_λ(i) ×ₘ S_i ṡ_i and
the backward one f_λ(i) += f_i are sums over each body's ancestors and each joint's subtree,
computed here as products with the tree's static support mask (``Topology.joint_support``).

Generalised forces τ (6 + n,) are dual to ν: (base force [N], world; base torque about the
base origin [N m], world-aligned; joint torques [N m] or forces [N]). For Pinocchio's free flyer
(local velocity ν_pin = T ν with T = diag(Rᵀ, Rᵀ, 1)), τ = Tᵀ τ_pin.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3
from jaxmm.rigid_body.centroidal import inertials_world
from jaxmm.rigid_body.configuration import check_configuration, check_velocity
from jaxmm.rigid_body.kinematics import body_poses, joint_axes_world

GRAVITY = (0.0, 0.0, -9.81)  # [m/s²], Pinocchio's default and the tasks'


def _cross_motion(v, m):
    """Spatial cross product v ×ₘ m of motions (ω, v_O): (…, 6), (…, 6) → (…, 6)."""
    return jnp.concatenate(
        [jnp.cross(v[..., :3], m[..., :3]), jnp.cross(v[..., :3], m[..., 3:]) + jnp.cross(v[..., 3:], m[..., :3])], axis=-1
    )


def _cross_force(v, f):
    """Spatial cross product v ×* f of a motion (ω, v_O) and a force (n_O, f): (…, 6) → (…, 6)."""
    return jnp.concatenate(
        [jnp.cross(v[..., :3], f[..., :3]) + jnp.cross(v[..., 3:], f[..., 3:]), jnp.cross(v[..., :3], f[..., 3:])], axis=-1
    )


def _body_inertias(model, R_body, p_body):
    """Spatial inertia of each body about the world origin, world-aligned: (nb, 6, 6).

    An element of mass m, CoM c and rotational inertia I_c contributes
    [[I_c + m S(c) S(c)ᵀ, m S(c)], [m S(c)ᵀ, m 1]] (Featherstone eq. 2.63)."""
    com, inertia = inertials_world(model, R_body, p_body)
    mass = model.inertial_mass
    S = jax.vmap(so3.skew)(com)
    rotational = inertia + mass[:, None, None] * S @ jnp.swapaxes(S, 1, 2)
    coupling = mass[:, None, None] * S
    linear = mass[:, None, None] * jnp.eye(3)
    elements = jnp.concatenate(
        [jnp.concatenate([rotational, coupling], axis=2), jnp.concatenate([jnp.swapaxes(coupling, 1, 2), linear], axis=2)],
        axis=1,
    )
    owner = np.zeros((len(model.topology.body_names), len(model.topology.inertial_body)))
    owner[np.asarray(model.topology.inertial_body, int), np.arange(owner.shape[1])] = 1.0
    return jnp.einsum("be,eij->bij", owner, elements)


def _joint_motion_axes(model, R_body, p_body):
    """Motion subspace S_j of each moving joint in ground coordinates: (nb − 1, 6).

    Revolute about the unit axis z through o: (z, o × z); prismatic along z: (0, z)."""
    axes, origins = joint_axes_world(model, R_body, p_body)
    prismatic = np.asarray(model.topology.joint_is_prismatic, bool)[:, None]
    angular = jnp.where(prismatic, 0.0, axes)
    linear = jnp.where(prismatic, axes, jnp.cross(origins, axes))
    return jnp.concatenate([angular, linear], axis=1)


def _all_joints(model, values):
    """Values (n,) of the optimised joints spread over every moving joint (locked ones 0)."""
    return jnp.zeros(len(model.topology.joint_names), values.dtype).at[np.asarray(model.topology.optimised_joints, int)].set(values)


def _external_wrenches(model, forces, frames, positions):
    """Forces (k, 3) [N] at frame origins (k, 3) [m] as spatial forces (r × F, F) summed per body:
    (nb, 6)."""
    owner = np.zeros((len(model.topology.body_names), len(frames)))
    owner[np.asarray(model.topology.frame_body, int)[list(frames)], np.arange(len(frames))] = 1.0
    return jnp.asarray(owner) @ jnp.concatenate([jnp.cross(positions, forces), forces], axis=1)


def inverse_dynamics(model, q, nu, nu_dot, forces=None, frames=(), gravity=GRAVITY):
    """Generalised forces τ = M(q) ν̇ + h(q, ν) − Σ_k J_k(q)ᵀ F_k by the recursive Newton–Euler
    algorithm (Featherstone, Table 5.1, in ground coordinates).

    q: (7 + n,); nu ν = (ṗ, ω, ṡ) and nu_dot ν̇ = (p̈, ω̇, s̈): (6 + n,), the mixed velocity and its
    time derivative (world-aligned; ``model``'s conventions). forces: (k, 3) pure forces [N],
    world frame, applied to the robot at the origins of ``frames`` (k names or indices, static),
    such as contact forces at sole corners and jet thrusts (eq. 5); J_k is the frame's linear
    Jacobian. gravity: (3,) [m/s²].

    Returns τ (6 + n,): the base force [N] (world), the base torque about the base origin [N m]
    (world-aligned), then the optimised joints' torques [N m] (forces [N] for prismatic joints).
    For a floating base the first six are the wrench that the external forces leave unbalanced:
    zero for a motion that the forces, thrusts and gravity can produce.
    """
    q = check_configuration(model, q)
    nu, nu_dot = check_velocity(model, nu), check_velocity(model, nu_dot)
    topology = model.topology
    R_body, p_body = body_poses(model, q)
    p, omega = q[:3], nu[3:6]
    # The base motion at the world origin: v_O = ṗ − ω × p; its derivative, with −g added so
    # that gravity enters every body's acceleration (Featherstone §5.3).
    base_velocity = jnp.concatenate([omega, nu[:3] - jnp.cross(omega, p)])
    base_acceleration = jnp.concatenate(
        [nu_dot[3:6], nu_dot[:3] - jnp.cross(nu_dot[3:6], p) - jnp.cross(omega, nu[:3]) - jnp.asarray(gravity, q.dtype)]
    )
    S = _joint_motion_axes(model, R_body, p_body)
    support = jnp.asarray(topology.joint_support, q.dtype)  # (nb − 1, nb)
    joint_velocity = S * _all_joints(model, nu[6:])[:, None]  # S_j ṡ_j
    velocity = base_velocity + support.T @ joint_velocity  # (nb, 6)
    parent_velocity = velocity[np.asarray(topology.body_parent[1:], int)]  # v_λ of each joint
    increments = S * _all_joints(model, nu_dot[6:])[:, None] + _cross_motion(parent_velocity, joint_velocity)
    acceleration = base_acceleration + support.T @ increments
    inertia = _body_inertias(model, R_body, p_body)
    body_force = jnp.einsum("bij,bj->bi", inertia, acceleration) + _cross_force(
        velocity, jnp.einsum("bij,bj->bi", inertia, velocity)
    )
    if forces is not None:
        frames = model.frame_indices(frames)
        forces = jnp.asarray(forces, q.dtype)
        if forces.shape != (len(frames), 3):
            raise ValueError(f"forces must have shape ({len(frames)}, 3), one per frame; got {forces.shape}")
        bodies = np.asarray(topology.frame_body, int)[list(frames)]
        positions = p_body[bodies] + jnp.einsum("kij,kj->ki", R_body[bodies], model.frame_translation[np.asarray(frames, int)])
        body_force = body_force - _external_wrenches(model, forces, frames, positions)
    subtree_force = support @ body_force  # (nb − 1, 6): the force each joint transmits
    joint_torque = jnp.sum(S * subtree_force, axis=1)[np.asarray(topology.optimised_joints, int)]
    total = jnp.sum(body_force, axis=0)  # (n_O, f) on the base, at the world origin
    base = jnp.concatenate([total[3:], total[:3] - jnp.cross(p, total[3:])])
    return jnp.concatenate([base, joint_torque])


def mass_matrix(model, q):
    """Joint-space inertia matrix M(q) for the mixed velocity: (7 + n,) → (6 + n, 6 + n),
    symmetric positive definite; ½ νᵀ M ν is the kinetic energy [J]. Its first three rows are
    the CMM's linear rows m J_com (eq. 4). Computed as ∂τ/∂ν̇ of ``inverse_dynamics`` at ν = 0
    without gravity (τ is affine in ν̇)."""
    q = check_configuration(model, q)
    zero = jnp.zeros(model.nv, q.dtype)
    return jax.jacfwd(lambda a: inverse_dynamics(model, q, zero, a, gravity=(0.0, 0.0, 0.0)))(zero)


def bias_forces(model, q, nu, gravity=GRAVITY):
    """h(q, ν) = C(q, ν) ν + g(q): ``inverse_dynamics`` at ν̇ = 0 without external forces, (6 + n,)."""
    return inverse_dynamics(model, q, nu, jnp.zeros_like(check_velocity(model, nu)), gravity=gravity)
