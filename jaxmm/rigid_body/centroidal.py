"""Total mass, centre of mass and the centroidal momentum matrix (eq. 4, 15, 16)."""

import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3
from jaxmm.rigid_body.configuration import check_velocity
from jaxmm.rigid_body.kinematics import body_poses, joint_axes_world


def total_mass(model):
    """Total mass m [kg] (a differentiable scalar)."""
    return jnp.sum(model.inertial_mass)


def _in_world(R_body, p_body, bodies, com, inertia):
    """Inertials given in their bodies' frames (CoM (k, 3), inertia about it (k, 3, 3)) moved to
    the world: world CoM (k, 3) and world-aligned inertia R I Rᵀ (k, 3, 3)."""
    R = R_body[bodies]
    return p_body[bodies] + jnp.einsum("eij,ej->ei", R, com), R @ inertia @ jnp.swapaxes(R, 1, 2)


def inertials_world(model, R_body, p_body):
    """World CoM (ne, 3) and world-aligned inertia about that CoM (ne, 3, 3) of each element."""
    return _in_world(R_body, p_body, np.asarray(model.topology.inertial_body, int), model.inertial_com,
                     model.inertial_inertia)


def _body_composites(model):
    """Each body's inertial elements merged into one by the parallel-axis theorem: the bodies with
    mass (static indices, nm), their mass (nm,) [kg], CoM (nm, 3) [m] and inertia about it (nm, 3,
    3) [kg m²], in the body's frame. Pose-independent: the kinematics' derivatives then carry one
    element per body (iRonCub: 27 for 37)."""
    bodies, owner = np.unique(np.asarray(model.topology.inertial_body, int), return_inverse=True)
    group = np.eye(len(bodies))[owner].T  # (nm, ne): which element belongs to which body
    mass = group @ model.inertial_mass
    # A body whose elements weigh nothing (a URDF may say so) keeps its CoM at its origin.
    com = group @ (model.inertial_mass[:, None] * model.inertial_com) / jnp.where(mass > 0, mass, 1.0)[:, None]
    d = model.inertial_com - com[owner]
    shifted = model.inertial_inertia + model.inertial_mass[:, None, None] * (
        jnp.sum(d * d, axis=1)[:, None, None] * jnp.eye(3) - d[:, :, None] * d[:, None, :])
    return bodies, mass, com, jnp.einsum("be,eij->bij", group, shifted)


def body_inertials_world(model, R_body, p_body):
    """Each body's inertial elements merged into one (the parallel-axis theorem), in the world:
    the bodies with mass (static indices, nm), their mass (nm,) [kg], world CoM (nm, 3) [m] and
    world-aligned inertia about it (nm, 3, 3) [kg m²], from the body poses (``body_poses``).
    The same total mass, first and second moments as ``inertials_world``'s elements."""
    bodies, mass, com, inertia = _body_composites(model)
    return (bodies, mass) + _in_world(R_body, p_body, bodies, com, inertia)


def com_position(model, q):
    """Centre of mass x(q) of eq. (15), world frame [m]: (7 + n,) → (3,)."""
    R_body, p_body = body_poses(model, q)
    com, _ = inertials_world(model, R_body, p_body)
    return model.inertial_mass @ com / total_mass(model)


def centroidal_momentum_matrix(model, q):
    """Centroidal momentum matrix J_CMM(q) of eq. (4): (7 + n,) → (6, 6 + n).

    h = J_CMM(q) ν is the momentum [linear (kg m/s); angular (kg m²/s)] of the robot about its
    CoM, in a frame with the world's orientation (the paper's frame G), for the mixed velocity
    ν = (ṗ, ω, ṡ). The linear rows equal m·J_com.

    Each column is computed from the composite mass, first moment and inertia (about the CoM)
    of the subtree the joint moves, so the cost is linear in the number of links.
    """
    R_body, p_body = body_poses(model, q)
    return _cmm_from_poses(model, q, R_body, p_body, body_inertials_world(model, R_body, p_body))


def _cmm_from_poses(model, q, R_body, p_body, composites):
    """J_CMM(q) from the body poses and ``body_inertials_world`` at them."""
    bodies, mass, com, inertia = composites
    m = jnp.sum(mass)
    x = mass @ com / m
    r = com - x  # the bodies' CoMs relative to the robot CoM
    # Inertia of each body about the robot CoM: I_b + m_b (|r|² I − r rᵀ).
    about_com = inertia + mass[:, None, None] * (
        jnp.sum(r * r, axis=1)[:, None, None] * jnp.eye(3) - r[:, :, None] * r[:, None, :]
    )
    moment = mass[:, None] * r  # first moments about the CoM

    # Base: ṗ translates everything; ω rotates everything about the base origin.
    base_linear = jnp.concatenate([m * jnp.eye(3), jnp.zeros((3, 3))])
    base_angular = jnp.concatenate([-m * so3.skew(x - q[:3]), jnp.sum(about_com, axis=0)])

    # Joint j moves its subtree: composite mass, first moment and inertia from a static mask.
    support = model.topology.joint_support[:, bodies].astype(float)
    subtree_mass = support @ mass  # (nj,)
    subtree_moment = support @ moment  # (nj, 3): Σ m_e (c_e − x)
    subtree_inertia = jnp.einsum("je,eab->jab", support, about_com)  # (nj, 3, 3)
    axes, origins = joint_axes_world(model, R_body, p_body)
    lever = x - origins  # (nj, 3): from each joint axis to the robot CoM
    # Revolute: v_e = z × (c_e − o) = z × (r_e + lever); prismatic: v_e = z.
    revolute_linear = jnp.cross(axes, subtree_moment + subtree_mass[:, None] * lever)
    revolute_angular = jnp.einsum("jab,jb->ja", subtree_inertia, axes) + jnp.cross(
        subtree_moment, jnp.cross(axes, lever)
    )
    prismatic = np.asarray(model.topology.joint_is_prismatic, bool)[:, None]
    linear = jnp.where(prismatic, subtree_mass[:, None] * axes, revolute_linear)
    angular = jnp.where(prismatic, jnp.cross(subtree_moment, axes), revolute_angular)
    joints = jnp.concatenate([linear, angular], axis=1)[np.asarray(model.topology.optimised_joints, int)].T
    return jnp.concatenate([base_linear, base_angular, joints], axis=1)


def bundle_from_poses(model, q, R_body, p_body, frames, composites=None):
    """The centroidal transcription's kinematics at q from the body poses (``body_poses``):
    {com (3,), cmm (6, 6 + n), frame_positions (k, 3), frame_rotations (k, 3, 3)} for frames
    (indices, static), as ``com_position``, ``centroidal_momentum_matrix`` and ``frame_poses``
    give them. composites: ``body_inertials_world`` at these poses, if already known."""
    composites = body_inertials_world(model, R_body, p_body) if composites is None else composites
    _, mass, com, _ = composites
    bodies = np.asarray(model.topology.frame_body, int)[list(frames)]
    indices = np.asarray(frames, int)
    positions = p_body[bodies] + jnp.einsum("fij,fj->fi", R_body[bodies], model.frame_translation[indices])
    rotations = R_body[bodies] @ model.frame_rotation[indices]
    return dict(
        com=mass @ com / jnp.sum(mass),
        cmm=_cmm_from_poses(model, q, R_body, p_body, composites),
        frame_positions=positions,
        frame_rotations=rotations,
    )


def com_jacobian(model, q):
    """Jacobian of the CoM for the mixed velocity, ẋ = J_com ν: (7 + n,) → (3, 6 + n)."""
    return centroidal_momentum_matrix(model, q)[:3] / total_mass(model)


def centroidal_momentum(model, q, nu):
    """Centroidal momentum h = J_CMM(q) ν (eq. 4): (7 + n,), (6 + n,) → (6,) [linear; angular]."""
    return centroidal_momentum_matrix(model, q) @ check_velocity(model, nu)
