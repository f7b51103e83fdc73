"""Rigid-body quantities against Pinocchio at 50 random configurations, to 1e-10 (relative to\nthe largest entry for forces and momenta)."""

import functools

import jax
import numpy as np
import pytest

import jaxmm
from conftest import random_configurations

COUNT = 50
TOL = 1e-10


@pytest.fixture(scope="module")
def sample(robot_pair):
    model, twin = robot_pair
    Q = random_configurations(model, COUNT, seed=7)
    V = np.random.default_rng(8).normal(size=(COUNT, model.nv))
    return model, twin, Q, V


def test_total_mass(sample):
    model, twin, _, _ = sample
    assert abs(float(jaxmm.total_mass(model)) - twin.pin.computeTotalMass(twin.model)) <= TOL


def test_frame_poses_every_frame(sample):
    model, twin, Q, _ = sample
    positions, rotations = jax.jit(jax.vmap(functools.partial(jaxmm.frame_poses, model)))(Q)
    ids = [twin.frame_id(name) for name in model.frame_names]
    worst = 0.0
    for q, P, R in zip(Q, np.asarray(positions), np.asarray(rotations)):
        twin.pin.framesForwardKinematics(twin.model, twin.data, twin.configuration(q))
        for k, fid in enumerate(ids):
            placement = twin.data.oMf[fid]
            worst = max(worst, np.abs(placement.translation - P[k]).max(), np.abs(placement.rotation - R[k]).max())
    assert len(ids) > 60  # every link of the robot is checked, not a handful
    assert worst <= TOL


def test_com_position(sample):
    model, twin, Q, _ = sample
    com = np.asarray(jax.jit(jax.vmap(functools.partial(jaxmm.com_position, model)))(Q))
    reference = np.array([twin.pin.centerOfMass(twin.model, twin.data, twin.configuration(q)) for q in Q])
    assert np.abs(com - reference).max() <= TOL


def test_centroidal_momentum(sample):
    model, twin, Q, V = sample
    h = np.asarray(jax.jit(jax.vmap(functools.partial(jaxmm.centroidal_momentum, model)))(Q, V))
    worst = 0.0
    for q, nu, h_q in zip(Q, V, h):
        A = twin.pin.computeCentroidalMap(twin.model, twin.data, twin.configuration(q))
        reference = A @ twin.velocity(q, nu)
        worst = max(worst, np.abs(h_q - reference).max() / max(1.0, np.abs(reference).max()))
    assert worst <= TOL


@pytest.mark.parametrize("frame", ["l_sole_1", "r_sole_3", "l_arm_jet_turbine", "chest_r_jet_turbine", "head"])
def test_frame_jacobian(sample, frame):
    model, twin, Q, V = sample
    J = np.asarray(jax.jit(jax.vmap(lambda q: jaxmm.frame_jacobian(model, q, frame)))(Q))
    pin = twin.pin
    fid = twin.frame_id(frame)
    worst = 0.0
    for q, nu, J_q in zip(Q, V, J):
        J_pin = pin.computeFrameJacobian(twin.model, twin.data, twin.configuration(q), fid, pin.LOCAL_WORLD_ALIGNED)
        worst = max(worst, np.abs(J_q @ nu - J_pin @ twin.velocity(q, nu)).max())
    assert worst <= TOL


FORCE_FRAMES = ("l_sole_1", "r_sole_3", "l_arm_jet_turbine", "chest_r_jet_turbine", "head")


@pytest.mark.parametrize("with_forces", [False, True], ids=["free", "external forces"])
def test_inverse_dynamics(sample, with_forces):
    """τ = Tᵀ rnea_pin(q, T ν, d/dt (T ν), fext): the recursive Newton–Euler algorithm, with pure
    forces at sole corners, jets and the head as Pinocchio's per-joint external forces."""
    model, twin, Q, V = sample
    rng = np.random.default_rng(9)
    A = rng.normal(size=V.shape)
    F = rng.normal(scale=100.0, size=(COUNT, len(FORCE_FRAMES), 3)) if with_forces else np.zeros((COUNT, 0, 3))
    frames = FORCE_FRAMES if with_forces else ()
    tau = np.asarray(jax.jit(jax.vmap(lambda q, v, a, f: jaxmm.inverse_dynamics(model, q, v, a, f, frames)))(Q, V, A, F))
    worst = 0.0
    for q, nu, nu_dot, forces, tau_q in zip(Q, V, A, F, tau):
        fext = twin.external_forces(q, frames, forces)
        tau_pin = twin.pin.rnea(twin.model, twin.data, twin.configuration(q), twin.velocity(q, nu),
                                twin.acceleration(q, nu, nu_dot), fext)
        reference = twin.velocity_map(q).T @ tau_pin
        worst = max(worst, np.abs(tau_q - reference).max() / max(1.0, np.abs(reference).max()))
    assert worst <= TOL


def test_mass_matrix(sample):
    """M = Tᵀ crba_pin(q) T (Pinocchio fills the upper triangle)."""
    model, twin, Q, _ = sample
    M = np.asarray(jax.jit(jax.vmap(functools.partial(jaxmm.mass_matrix, model)))(Q))
    worst = 0.0
    for q, M_q in zip(Q, M):
        upper = twin.pin.crba(twin.model, twin.data, twin.configuration(q))
        T = twin.velocity_map(q)
        reference = T.T @ (np.triu(upper) + np.triu(upper, 1).T) @ T
        worst = max(worst, np.abs(M_q - reference).max() / np.abs(reference).max())
    assert worst <= TOL
