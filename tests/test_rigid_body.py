"""Identities, autodiff checks and vmap equivalence of kinematics, CoM and the CMM."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxmm
from conftest import assert_kinematics_derivatives_equal_autodiff, random_configurations

FRAMES = ("l_sole_1", "l_sole_2", "l_sole_3", "l_sole_4", "r_sole_1", "r_sole_2", "r_sole_3", "r_sole_4",
          "l_arm_jet_turbine", "r_arm_jet_turbine", "chest_l_jet_turbine", "chest_r_jet_turbine")


@pytest.fixture(scope="module")
def model(ironcub):
    return ironcub.model


@pytest.fixture(scope="module")
def configurations(model):
    return random_configurations(model, 8, seed=3)


def test_total_mass_is_sum_of_link_masses(ironcub):
    description = jaxmm.robots.ironcub_description()
    urdf = jaxmm.assemble_urdf(description)
    masses = [link.inertial.mass for link in urdf.robot.links if link.inertial is not None]
    assert np.isclose(float(jaxmm.total_mass(ironcub.model)), sum(masses), rtol=0, atol=1e-12)


def test_linear_rows_of_cmm_are_mass_times_com_jacobian(model, configurations):
    """m·ẋ from the CMM equals m·d/dt com(q(t)), the latter by forward-mode autodiff of x(q)."""
    rng = np.random.default_rng(4)
    m = jaxmm.total_mass(model)
    com = functools.partial(jaxmm.com_position, model)
    com_velocity = jax.jit(lambda q, q_dot: jax.jvp(com, (q,), (q_dot,))[1])
    cmm = jax.jit(functools.partial(jaxmm.centroidal_momentum_matrix, model))
    for q in configurations:
        nu = rng.normal(size=model.nv)
        q_dot = jaxmm.configuration_derivative(q, nu)
        x_dot = com_velocity(q, q_dot)
        A = cmm(q)
        assert np.allclose(A[:3] @ nu, m * x_dot, atol=1e-12, rtol=0)
        assert np.allclose(A[:3], m * jaxmm.com_jacobian(model, q), atol=1e-12)


def test_frame_jacobian_is_derivative_of_frame_position(model, configurations):
    rng = np.random.default_rng(5)
    for q in configurations[:3]:
        nu = rng.normal(size=model.nv)
        for frame in ("l_sole_1", "chest_l_jet_turbine"):
            position = lambda q: jaxmm.frame_pose(model, q, frame)[0]  # noqa: E731
            rotation = lambda q: jaxmm.frame_pose(model, q, frame)[1]  # noqa: E731
            q_dot = jaxmm.configuration_derivative(q, nu)
            _, v = jax.jvp(position, (q,), (q_dot,))
            R, R_dot = jax.jvp(rotation, (q,), (q_dot,))
            omega_hat = R_dot @ R.T  # Ṙ = S(ω) R
            omega = jnp.array([omega_hat[2, 1], omega_hat[0, 2], omega_hat[1, 0]])
            J = jaxmm.frame_jacobian(model, q, frame)
            assert np.allclose(J @ nu, jnp.concatenate([v, omega]), atol=1e-12)


def test_cmm_of_rigid_motion(model, configurations):
    """A pure base translation gives h = (m ṗ, 0); joint velocities alone leave m ẋ = J_com ṡ,
    ẋ the derivative of com(q(t)) by forward-mode autodiff with the base at rest."""
    q = configurations[0]
    m = jaxmm.total_mass(model)
    p_dot = np.array([0.3, -1.0, 2.0])
    nu = np.concatenate([p_dot, np.zeros(model.nv - 3)])
    h = jaxmm.centroidal_momentum(model, q, nu)
    assert np.allclose(h, np.concatenate([m * p_dot, np.zeros(3)]), atol=1e-12)
    s_dot = np.random.default_rng(8).normal(size=model.nv - 6)
    nu = np.concatenate([np.zeros(6), s_dot])
    _, x_dot = jax.jvp(functools.partial(jaxmm.com_position, model), (q,), (np.concatenate([np.zeros(7), s_dot]),))
    h = jaxmm.centroidal_momentum(model, q, nu)
    assert np.linalg.norm(x_dot) > 0.01  # the joints move the CoM: the check has something to match
    assert np.allclose(h[:3], m * x_dot, atol=1e-12)
    assert np.allclose(h[:3], m * jaxmm.com_jacobian(model, q)[:, 6:] @ s_dot, atol=1e-12)


def test_body_composites_keep_mass_first_and_second_moments(model, configurations):
    """Each body's merged inertial (the CMM's elements) has its elements' mass, first moment and
    inertia about the robot CoM, in the world at any pose (the parallel-axis theorem)."""
    from jaxmm.rigid_body import centroidal
    from jaxmm.rigid_body.kinematics import body_poses

    elements = np.asarray(model.topology.inertial_body, int)
    assert len(np.unique(elements)) < len(elements)  # some body has several: the merge does something
    for q in configurations[:3]:
        R_body, p_body = body_poses(model, q)
        com, inertia = centroidal.inertials_world(model, R_body, p_body)
        bodies, mass, merged_com, merged_inertia = centroidal.body_inertials_world(model, R_body, p_body)
        x = jaxmm.com_position(model, q)

        def about_x(m, c, inertia):
            r = c - x
            return inertia + m[:, None, None] * (np.sum(r * r, 1)[:, None, None] * np.eye(3) - r[:, :, None] * r[:, None, :])

        for k, body in enumerate(bodies):
            own = elements == body
            assert np.isclose(mass[k], np.sum(model.inertial_mass[own]), rtol=1e-15)
            assert np.allclose(mass[k] * merged_com[k], model.inertial_mass[own] @ com[own], rtol=0, atol=1e-14)
            assert np.allclose(about_x(mass[k:k + 1], merged_com[k:k + 1], merged_inertia[k:k + 1])[0],
                               np.sum(about_x(model.inertial_mass[own], com[own], inertia[own]), 0), rtol=0, atol=1e-13)


def test_a_massless_link_keeps_the_momentum_finite():
    """A link of zero mass with an inertia (a URDF may say so): two unit-inertia links on a z
    hinge, the base of 2 kg at the CoM, give h = (2 ṗ, ω + (ω + ṡ e_z)) exactly."""
    inertial = '<inertial><origin xyz="0 0 0" rpy="0 0 0"/><mass value="{}"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial>'
    xml = (f'<robot name="massless"><link name="l0">{inertial.format(2.0)}</link><link name="l1">{inertial.format(0.0)}</link>'
           '<joint name="j1" type="revolute"><parent link="l0"/><child link="l1"/><origin xyz="0 0 0" rpy="0 0 0"/>'
           '<axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint></robot>')
    model = jaxmm.load_robot(xml).model
    q, nu = np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 0.5]), np.arange(7.0)
    h = np.asarray(jaxmm.centroidal_momentum(model, q, nu))
    assert np.allclose(h, np.concatenate([2 * nu[:3], 2 * nu[3:6] + nu[6] * np.eye(3)[2]]), rtol=0, atol=1e-14)


def test_vmap_matches_single_calls(model, configurations):
    Q = jnp.asarray(configurations)
    nu = jnp.asarray(np.random.default_rng(6).normal(size=(len(Q), model.nv)))
    functions = {
        "com": lambda q, v: jaxmm.com_position(model, q),
        "cmm": lambda q, v: jaxmm.centroidal_momentum_matrix(model, q),
        "frames": lambda q, v: jaxmm.frame_poses(model, q, FRAMES),
        "jacobian": lambda q, v: jaxmm.frame_jacobian(model, q, "r_sole_2"),
        "integrate": lambda q, v: jaxmm.integrate_configuration(q, v, 0.05),
    }
    for name, f in functions.items():
        f = jax.jit(f)
        batched = jax.vmap(f)(Q, nu)
        for i in range(len(Q)):
            single = f(Q[i], nu[i])
            for b, s in zip(jax.tree.leaves(batched), jax.tree.leaves(single)):
                assert np.allclose(b[i], s, atol=1e-13, rtol=1e-13), name


def test_gradients_of_kinematics_and_cmm(model, configurations):
    q = jnp.asarray(configurations[1])
    check_grads(jax.jit(lambda q: jaxmm.frame_poses(model, q, FRAMES)), (q,), order=1, modes=["fwd", "rev"])
    check_grads(jax.jit(lambda q: jaxmm.com_position(model, q)), (q,), order=2, modes=["fwd", "rev"])
    nu = jnp.asarray(np.random.default_rng(1).normal(size=model.nv))
    check_grads(jax.jit(lambda q: jaxmm.centroidal_momentum(model, q, nu)), (q,), order=1, modes=["fwd", "rev"])


def test_kinematics_derivatives_by_the_tree_recursions_equal_autodiff(model, configurations):
    """``centroidal_kinematics_derivatives`` (the tree recursions) gives the kinematics, ``jax.jacfwd``
    of them and ``jax.hessian`` of their weighted sum, each through the plain kinematics, on iRonCub."""
    assert_kinematics_derivatives_equal_autodiff(model, FRAMES, configurations[:3], seed=6)


def test_gradients_with_respect_to_model_parameters(model, configurations):
    """Masses and placements are array leaves: the CoM is differentiable in them."""
    q = jnp.asarray(configurations[2])

    def com_of(masses, translations):
        changed = jax.tree_util.tree_map(lambda x: x, model)
        changed = type(model)(**{**changed.__dict__, "inertial_mass": masses, "joint_translation": translations})
        return jaxmm.com_position(changed, q)

    check_grads(com_of, (model.inertial_mass, model.joint_translation), order=1, modes=["fwd", "rev"])


def test_quaternion_integrator_gradient_at_zero_velocity(model, configurations):
    q = jnp.asarray(configurations[0])
    for nu in (jnp.zeros(model.nv), jnp.asarray(np.random.default_rng(2).normal(size=model.nv))):
        step = jax.jit(lambda nu: jaxmm.integrate_configuration(q, nu, 0.05))
        check_grads(step, (nu,), order=2, modes=["fwd", "rev"])
        grad = jax.jacrev(lambda nu: jaxmm.integrate_configuration(q, nu, 0.05))(nu)
        assert np.all(np.isfinite(grad))
        assert abs(np.linalg.norm(jaxmm.integrate_configuration(q, nu, 0.05)[3:7]) - 1) < 1e-14


def test_standing_pose_has_feet_on_the_ground(ironcub):
    positions, _ = jaxmm.frame_poses(ironcub.model, ironcub.standing_configuration, ironcub.contact_frames)
    assert np.abs(np.asarray(positions)[:, 2]).max() < 0.01
    assert np.all(np.isfinite(np.asarray(positions)))


def test_jit_with_static_model_fields(model, configurations):
    """The model is a pytree: passing it as a jit argument traces only its arrays. The traced
    program's inputs are the model's array leaves and q, and a model with other masses and
    inertias (scaled by 2: every momentum doubles) runs the same program without a new trace."""
    traces = []

    def cmm(model, q):
        traces.append(None)
        return jaxmm.centroidal_momentum_matrix(model, q)

    leaves = jax.tree.leaves(model)
    assert leaves and all(isinstance(leaf, jax.Array) for leaf in leaves)
    assert len(jax.make_jaxpr(cmm)(model, configurations[0]).jaxpr.invars) == len(leaves) + 1
    compiled = jax.jit(cmm)
    A = compiled(model, configurations[0])
    assert A.shape == (6, model.nv) and A.dtype == jnp.float64
    assert np.allclose(A, jaxmm.centroidal_momentum_matrix(model, configurations[0]))
    heavier = dataclasses.replace(model, inertial_mass=2 * model.inertial_mass,
                                  inertial_inertia=2 * model.inertial_inertia)
    traces.clear()
    assert np.allclose(compiled(heavier, configurations[0]), 2 * A, atol=1e-12)
    assert not traces


def _momentum_rate(model, q, nu, nu_dot):
    """ḣ = d/dt (J_CMM(q) ν) along q̇(q, ν) and ν̇, by forward-mode autodiff (eq. 4)."""
    cmm = functools.partial(jaxmm.centroidal_momentum_matrix, model)
    q_dot = jaxmm.configuration_derivative(q, nu)
    return jax.jvp(lambda q, nu: cmm(q) @ nu, (q, nu), (q_dot, nu_dot))[1]


def test_inverse_dynamics_base_wrench_is_the_momentum_rate(model, configurations):
    """Newton and Euler for the whole robot: without external forces, the base wrench of the
    recursive Newton–Euler algorithm, moved from the base origin to the CoM, equals the rate of
    the centroidal momentum minus gravity's force (eq. 13 with no contact or thrust)."""
    rng = np.random.default_rng(11)
    m = float(jaxmm.total_mass(model))
    gravity = np.array([0.0, 0.0, -9.81])
    inverse = jax.jit(functools.partial(jaxmm.inverse_dynamics, model))
    for q in configurations:
        nu, nu_dot = rng.normal(size=(2, model.nv))
        tau = np.asarray(inverse(q, nu, nu_dot))
        x = np.asarray(jaxmm.com_position(model, q))
        force, torque_at_com = tau[:3], tau[3:6] + np.cross(q[:3] - x, tau[:3])
        rate = np.asarray(_momentum_rate(model, q, nu, nu_dot))
        assert np.allclose(force, rate[:3] - m * gravity, rtol=0, atol=1e-10 * max(1.0, np.abs(rate).max()))
        assert np.allclose(torque_at_com, rate[3:], rtol=0, atol=1e-10 * max(1.0, np.abs(rate).max()))


def test_mass_matrix_identities(model, configurations):
    """M is symmetric positive definite; its base rows times ν are the momentum about the base
    origin, (m ẋ, h_ω + (x − p) × m ẋ); τ = M ν̇ + h(q, ν) (the bias forces)."""
    rng = np.random.default_rng(12)
    mass = jax.jit(functools.partial(jaxmm.mass_matrix, model))
    for q in configurations[:4]:
        M = np.asarray(mass(q))
        assert np.abs(M - M.T).max() <= 1e-12 * np.abs(M).max()
        assert np.linalg.eigvalsh(M).min() > 0
        nu, nu_dot = rng.normal(size=(2, model.nv))
        h = np.asarray(jaxmm.centroidal_momentum(model, q, nu))
        x = np.asarray(jaxmm.com_position(model, q))
        assert np.allclose(M[:3] @ nu, h[:3], rtol=0, atol=1e-12)
        assert np.allclose(M[3:6] @ nu, h[3:] + np.cross(x - q[:3], h[:3]), rtol=0, atol=1e-11)
        tau = np.asarray(jaxmm.inverse_dynamics(model, q, nu, nu_dot))
        assert np.allclose(tau, M @ nu_dot + np.asarray(jaxmm.bias_forces(model, q, nu)), rtol=0, atol=1e-10)


def test_inverse_dynamics_external_force_enters_through_the_jacobian(model, configurations):
    """A pure force F at a frame subtracts J_linearᵀ F from τ (the frame's mixed Jacobian)."""
    rng = np.random.default_rng(13)
    for q in configurations[:3]:
        nu, nu_dot = rng.normal(size=(2, model.nv))
        force = rng.normal(scale=30.0, size=(1, 3))
        free = jaxmm.inverse_dynamics(model, q, nu, nu_dot)
        pushed = jaxmm.inverse_dynamics(model, q, nu, nu_dot, force, ("r_sole_2",))
        J = jaxmm.frame_jacobian(model, q, "r_sole_2")
        assert np.allclose(free - pushed, J[:3].T @ force[0], rtol=0, atol=1e-10)


def test_inverse_dynamics_vmap_and_gradients(model, configurations):
    """vmap equals a loop; derivatives in q, ν, ν̇ and the forces match finite differences."""
    rng = np.random.default_rng(14)
    frames = ("l_sole_1", "chest_l_jet_turbine")
    Q = configurations[:3]
    V, A = rng.normal(size=(2, 3, model.nv))
    F = rng.normal(scale=20.0, size=(3, 2, 3))
    inverse = lambda q, v, a, f: jaxmm.inverse_dynamics(model, q, v, a, f, frames)  # noqa: E731
    batched = np.asarray(jax.jit(jax.vmap(inverse))(Q, V, A, F))
    looped = np.stack([np.asarray(inverse(*args)) for args in zip(Q, V, A, F)])
    assert np.allclose(batched, looped, rtol=0, atol=1e-12)
    check_grads(inverse, (Q[0], V[0], A[0], F[0]), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def test_inverse_dynamics_rejects_forces_of_the_wrong_shape(model, configurations):
    with pytest.raises(ValueError, match=r"forces must have shape \(2, 3\)"):
        jaxmm.inverse_dynamics(model, configurations[0], np.zeros(model.nv), np.zeros(model.nv), np.zeros((3, 3)),
                               ("l_sole_1", "head"))
