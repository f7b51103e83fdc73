"""Rotations: skew matrices, unit quaternions and the exponential map of SO(3).

Quaternions are stored **(x, y, z, w)**, scalar last (the paper's ρ, and Pinocchio's order).
Every function acts on one sample (batch with ``jax.vmap``) and is safe to differentiate at
the identity (ω = 0): the small-angle branches use Taylor series behind a double ``where`` so
that no NaN reaches a gradient. ``log`` is exact up to (and including) rotations by π.
"""

import jax.numpy as jnp

# Below this squared angle the Taylor expansions are exact to float64 rounding.
_SMALL_ANGLE_SQ = 1e-8


def skew(v):
    """Skew-symmetric matrix S(v), with S(v) u = v × u (the paper's S(·), eq. 1).

    v: (3,) → (3, 3).
    """
    x, y, z = v[0], v[1], v[2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]), jnp.stack([-y, x, zero])]
    )


def quaternion_multiply(a, b):
    """Hamilton product a ⊗ b of quaternions (x, y, z, w): (4,), (4,) → (4,)."""
    av, aw = a[:3], a[3]
    bv, bw = b[:3], b[3]
    vector = aw * bv + bw * av + jnp.cross(av, bv)
    return jnp.concatenate([vector, (aw * bw - av @ bv)[None]])


def quaternion_conjugate(q):
    """Conjugate (−x, −y, −z, w): the inverse of a unit quaternion. (4,) → (4,)."""
    return jnp.concatenate([-q[:3], q[3:]])


def quaternion_to_rotation(q):
    """Rotation matrix of a unit quaternion (x, y, z, w): (4,) → (3, 3).

    The quaternion is normalised first, so any non-zero quaternion gives a rotation.
    """
    q = q / jnp.linalg.norm(q)
    x, y, z, w = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)]),
            jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)]),
            jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]),
        ]
    )


def rotation_to_quaternion(R):
    """Unit quaternion (x, y, z, w) with w ≥ 0 of a rotation matrix: (3, 3) → (4,).

    Shepperd's method: of the four algebraically equal formulas, the one with the largest
    square root is used, which is always ≥ 1/2, so the result is accurate everywhere.
    """
    trace = jnp.trace(R)
    diag = jnp.diagonal(R)
    # 4·q_i² for i = x, y, z, w.
    candidates = jnp.concatenate([1 + 2 * diag - trace, (1 + trace)[None]])
    i = jnp.argmax(candidates)
    d = 0.5 * jnp.sqrt(jnp.max(candidates))  # |q_i|, ≥ 1/4
    s = 0.25 / d
    from_x = jnp.stack([d, (R[0, 1] + R[1, 0]) * s, (R[0, 2] + R[2, 0]) * s, (R[2, 1] - R[1, 2]) * s])
    from_y = jnp.stack([(R[0, 1] + R[1, 0]) * s, d, (R[1, 2] + R[2, 1]) * s, (R[0, 2] - R[2, 0]) * s])
    from_z = jnp.stack([(R[0, 2] + R[2, 0]) * s, (R[1, 2] + R[2, 1]) * s, d, (R[1, 0] - R[0, 1]) * s])
    from_w = jnp.stack([(R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s, (R[1, 0] - R[0, 1]) * s, d])
    q = jnp.stack([from_x, from_y, from_z, from_w])[i]
    return jnp.where(q[3] < 0, -q, q)


def _angle_and_safe_angle(w):
    """θ = ‖w‖, its square, and a θ that is never 0 (for the large-angle branch)."""
    theta_sq = w @ w
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_theta = jnp.sqrt(jnp.where(small, 1.0, theta_sq))
    return theta_sq, small, safe_theta


def exp(w):
    """Exp of SO(3) (Rodrigues): rotation vector w (3,) [rad] → rotation matrix (3, 3)."""
    theta_sq, small, theta = _angle_and_safe_angle(w)
    sin_over = jnp.where(small, 1 - theta_sq / 6 + theta_sq**2 / 120, jnp.sin(theta) / theta)
    one_minus_cos_over = jnp.where(
        small, 0.5 - theta_sq / 24 + theta_sq**2 / 720, (1 - jnp.cos(theta)) / theta**2
    )
    S = skew(w)
    return jnp.eye(3) + sin_over * S + one_minus_cos_over * (S @ S)


def quaternion_exp(w):
    """Exp of SO(3) as a unit quaternion (x, y, z, w): rotation vector (3,) → (4,)."""
    theta_sq, small, theta = _angle_and_safe_angle(w)
    half_sin_over = jnp.where(
        small, 0.5 - theta_sq / 48 + theta_sq**2 / 3840, jnp.sin(theta / 2) / theta
    )
    half_cos = jnp.where(small, 1 - theta_sq / 8 + theta_sq**2 / 384, jnp.cos(theta / 2))
    return jnp.concatenate([half_sin_over * w, half_cos[None]])


def quaternion_log(q):
    """Log of SO(3) from a unit quaternion: (4,) → rotation vector (3,) with angle in [0, π].

    q and −q give the same result (both are the same rotation).
    """
    q = jnp.where(q[3] < 0, -q, q)
    v, w = q[:3], q[3]
    n_sq = v @ v
    small = n_sq < _SMALL_ANGLE_SQ
    n = jnp.sqrt(jnp.where(small, 1.0, n_sq))
    # 2·atan2(n, w)/n, with its Taylor series in n where n → 0 (then w → 1).
    w_safe = jnp.where(small, w, 1.0)
    scale = jnp.where(
        small,
        2 / w_safe - 2 * n_sq / (3 * w_safe**3),
        2 * jnp.arctan2(n, w) / n,
    )
    return scale * v


def log(R):
    """Log of SO(3): rotation matrix (3, 3) → rotation vector (3,), angle in [0, π]."""
    return quaternion_log(rotation_to_quaternion(R))


def quaternion_integrate(rho, omega, dt):
    """The ⊕ integrator of eq. (25b): ρ⁺ = Exp(ω Δt) ⊗ ρ.

    rho: (4,) unit quaternion (x, y, z, w), base to world; omega: (3,) angular velocity in
    the world frame [rad/s]; dt: time step [s]. Returns a unit quaternion (4,).
    """
    return quaternion_multiply(quaternion_exp(omega * dt), rho)
