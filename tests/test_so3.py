"""SO(3) and quaternion operations: identities, Pinocchio, hypothesis properties, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxmm  # noqa: F401  (enables float64)
from jaxmm.rigid_body import so3

vectors = st.lists(st.floats(-10, 10, allow_nan=False), min_size=3, max_size=3).map(np.array)
quaternions = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4)
    .map(np.array)
    .filter(lambda q: np.linalg.norm(q) > 1e-3)
    .map(lambda q: q / np.linalg.norm(q))
)
# Rotation vectors with angle in [0, π): Log(Exp(w)) = w holds only there.
rotation_vectors = st.tuples(vectors.filter(lambda v: np.linalg.norm(v) > 1e-6), st.floats(0, np.pi - 1e-6)).map(
    lambda a: a[0] / np.linalg.norm(a[0]) * a[1]
)
small = st.floats(-1e-5, 1e-5).flatmap(lambda scale: vectors.map(lambda v: v * scale))


def test_exp_of_zero_is_identity():
    assert np.array_equal(so3.exp(jnp.zeros(3)), np.eye(3))
    assert np.array_equal(so3.quaternion_exp(jnp.zeros(3)), np.array([0.0, 0.0, 0.0, 1.0]))


@settings(max_examples=200, deadline=None)
@given(rotation_vectors)
def test_log_exp_roundtrip(w):
    assert np.allclose(so3.log(so3.exp(w)), w, atol=1e-9)
    assert np.allclose(so3.quaternion_log(so3.quaternion_exp(w)), w, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(small)
def test_log_exp_roundtrip_near_zero(w):
    assert np.allclose(so3.log(so3.exp(w)), w, atol=1e-15, rtol=1e-9)


@settings(max_examples=100, deadline=None)
@given(vectors)
def test_exp_and_log_against_pinocchio(w):
    pin = pytest.importorskip("pinocchio")
    assert np.allclose(so3.exp(w), pin.exp3(w), atol=1e-12)
    R = pin.exp3(w)
    assert np.allclose(so3.exp(so3.log(R)), R, atol=1e-12)
    angle = np.linalg.norm(w) % (2 * np.pi)
    if 1e-3 < angle < np.pi - 1e-3:  # where pin.log3 is unambiguous
        assert np.allclose(so3.log(R), pin.log3(R), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quaternions, quaternions)
def test_quaternion_product_is_rotation_product(a, b):
    R = so3.quaternion_to_rotation
    assert np.allclose(R(so3.quaternion_multiply(a, b)), R(a) @ R(b), atol=1e-12)
    assert np.allclose(so3.quaternion_multiply(a, so3.quaternion_conjugate(a)), [0, 0, 0, 1], atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(quaternions)
def test_rotation_quaternion_roundtrip(q):
    R = so3.quaternion_to_rotation(q)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    back = so3.rotation_to_quaternion(R)
    assert back[3] >= 0
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) <= 1e-12  # q and −q: one rotation
    assert np.allclose(so3.quaternion_to_rotation(back), R, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(vectors, vectors)
def test_skew_is_cross_product(a, b):
    assert np.allclose(so3.skew(a) @ b, np.cross(a, b), atol=1e-12)
    assert np.array_equal(so3.skew(a), -so3.skew(a).T)


@settings(max_examples=200, deadline=None)
@given(quaternions, vectors, st.floats(0, 0.2))
def test_integrator_keeps_unit_norm(rho, omega, dt):
    rho_next = so3.quaternion_integrate(rho, omega, dt)
    assert abs(np.linalg.norm(rho_next) - 1) <= 1e-14
    # ρ⁺ = Exp(ωΔt) ⊗ ρ: the rotation is left-multiplied (ω in the world frame, eq. 25b).
    expected = np.asarray(so3.exp(omega * dt)) @ np.asarray(so3.quaternion_to_rotation(rho))
    assert np.allclose(so3.quaternion_to_rotation(rho_next), expected, atol=1e-12)


def test_log_near_pi():
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    for angle in [np.pi - 1e-4, np.pi - 1e-9, np.pi]:
        w = so3.log(so3.exp(angle * axis))
        assert np.isclose(np.linalg.norm(w), angle, atol=1e-9)
        assert np.allclose(np.abs(w / np.linalg.norm(w)), np.abs(axis), atol=1e-9)
    # Exactly π about a coordinate axis: R = diag(1, −1, −1).
    assert np.allclose(np.abs(so3.log(np.diag([1.0, -1.0, -1.0]))), [np.pi, 0, 0], atol=1e-12)


@pytest.mark.parametrize("w", [np.zeros(3), np.array([1e-7, -2e-7, 3e-8]), np.array([0.3, -1.2, 2.0])])
def test_gradients_are_finite_and_correct(w):
    check_grads(so3.exp, (w,), order=2, modes=["fwd", "rev"])
    check_grads(so3.quaternion_exp, (w,), order=2, modes=["fwd", "rev"])
    rho = np.array([0.1, -0.3, 0.2, 0.9]) / np.linalg.norm([0.1, -0.3, 0.2, 0.9])
    check_grads(lambda omega: so3.quaternion_integrate(rho, omega, 0.05), (w,), order=2, modes=["fwd", "rev"])
    check_grads(so3.log, (so3.exp(w),), order=1, modes=["fwd", "rev"])
    check_grads(so3.quaternion_log, (so3.quaternion_exp(w),), order=1, modes=["fwd", "rev"])
    for f in (so3.exp, so3.quaternion_exp, so3.log):
        grad = jax.jacrev(f)(w if f is not so3.log else so3.exp(w))
        assert np.all(np.isfinite(grad))


def test_gradient_at_zero_matches_analytic():
    # d Exp(w)/dw at 0 is the skew generator; d quaternion_exp/dw at 0 is ½ I (vector part).
    J = jax.jacfwd(so3.exp)(jnp.zeros(3))
    for i in range(3):
        assert np.allclose(J[:, :, i], so3.skew(np.eye(3)[i]))
    assert np.allclose(jax.jacfwd(so3.quaternion_exp)(jnp.zeros(3))[:3], 0.5 * np.eye(3))
