"""Total mass, centre of mass and the centroidal momentum matrix (eq. 4, 15, 16)."""

import jax.numpy as jnp
import numpy as np

from jaxmm import so3
from jaxmm.configuration import check_velocity
from jaxmm.kinematics import body_poses, joint_axes_world


def total_mass(model):
    """Total mass m [kg] (a differentiable scalar)."""
    return jnp.sum(model.inertial_mass)


def _inertials_world(model, R_body, p_body):
    """World CoM (ne, 3) and world-aligned inertia about that CoM (ne, 3, 3) of each element."""
    bodies = np.asarray(model.topology.inertial_body, int)
    R = R_body[bodies]
    com = p_body[bodies] + jnp.einsum("eij,ej->ei", R, model.inertial_com)
    inertia = R @ model.inertial_inertia @ jnp.swapaxes(R, 1, 2)
    return com, inertia


def com_position(model, q):
    """Centre of mass x(q) of eq. (15), world frame [m]: (7 + n,) → (3,)."""
    R_body, p_body = body_poses(model, q)
    com, _ = _inertials_world(model, R_body, p_body)
    return model.inertial_mass @ com / total_mass(model)


def centroidal_momentum_matrix(model, q):
    """Centroidal momentum matrix J_CMM(q) of eq. (4): (7 + n,) → (6, 6 + n).

    h = J_CMM(q) ν is the momentum [linear (kg m/s); angular (kg m²/s)] of the robot about its
    CoM, in a frame with the world's orientation (the paper's frame G), for the mixed velocity
    ν = (ṗ, ω, ṡ). The linear rows equal m·J_com.
    """
    R_body, p_body = body_poses(model, q)
    com, inertia = _inertials_world(model, R_body, p_body)
    mass = model.inertial_mass
    m = jnp.sum(mass)
    x = mass @ com / m
    r = com - x  # element CoMs relative to the robot CoM

    # Base linear velocity: every element moves with ṗ.
    base_linear = jnp.concatenate([m * jnp.eye(3), jnp.zeros((3, 3))])
    # Base angular velocity: the whole robot rotates rigidly about the base origin.
    S_r = jnp.vectorize(so3.skew, signature="(3)->(3,3)")(r)
    locked_inertia = jnp.sum(inertia, axis=0) - jnp.einsum("e,eij,ejk->ik", mass, S_r, S_r)
    base_angular = jnp.concatenate([-m * so3.skew(x - q[:3]), locked_inertia])

    # Each joint moves the elements of its subtree (static mask).
    axes, origins = joint_axes_world(model, R_body, p_body)
    support = model.topology.joint_support[:, np.asarray(model.topology.inertial_body, int)]
    prismatic = np.asarray(model.topology.joint_is_prismatic, bool)
    weights = jnp.where(support, mass[None, :], 0.0)  # (nj, ne)
    lever = com[None, :, :] - origins[:, None, :]
    velocity = jnp.where(
        prismatic[:, None, None], axes[:, None, :], jnp.cross(axes[:, None, :], lever)
    )  # (nj, ne, 3): velocity of each element CoM per unit joint rate
    linear = jnp.einsum("je,jei->ij", weights, velocity)
    spin = jnp.einsum("je,eik,jk->ij", support.astype(float), inertia, axes)
    spin = jnp.where(prismatic[None, :], 0.0, spin)
    angular = spin + jnp.einsum("je,jei->ij", weights, jnp.cross(r[None], velocity))
    joints = jnp.concatenate([linear, angular])[:, np.asarray(model.topology.optimised_joints, int)]
    return jnp.concatenate([base_linear, base_angular, joints], axis=1)


def com_jacobian(model, q):
    """Jacobian of the CoM for the mixed velocity, ẋ = J_com ν: (7 + n,) → (3, 6 + n)."""
    return centroidal_momentum_matrix(model, q)[:3] / total_mass(model)


def centroidal_momentum(model, q, nu):
    """Centroidal momentum h = J_CMM(q) ν (eq. 4): (7 + n,), (6 + n,) → (6,) [linear; angular]."""
    return centroidal_momentum_matrix(model, q) @ check_velocity(model, nu)
