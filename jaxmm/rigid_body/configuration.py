"""Configurations q = (p, ρ, s) and velocities ν = (ṗ, ω, ṡ); conventions in ``jaxmm.rigid_body.model``."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3

# |‖ρ‖ − 1| accepted in a configuration given by value: the kinematics normalise ρ, so a solver's
# drift is harmless; a norm off by more than this is a mistake (angles, zeros, a wrong layout).
QUATERNION_TOLERANCE = 1e-3


def _check_real(x, label):
    if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
        raise TypeError(f"{label} must be a real (float) array, got dtype {x.dtype}")


def check_configuration(model, q):
    """Return q as a float array after checking its shape (7 + n,) and dtype; raises
    ValueError (TypeError for a non-real dtype).

    A q given by value (not traced by ``jax.jit``/``grad``/``vmap``) is also checked for
    non-finite entries and a base quaternion ρ = q[3:7] of norm 1 within
    ``QUATERNION_TOLERANCE``. Traced q are not checked (their values are unknown when tracing).
    """
    q = jnp.asarray(q)
    _check_real(q, "configuration q")
    if q.shape != (model.nq,):
        raise ValueError(
            f"configuration q must have shape ({model.nq},) = 3 base position + 4 quaternion "
            f"(x, y, z, w) + {model.n_joints} joints of {model.name!r}, got {q.shape}"
        )
    if not isinstance(q, jax.core.Tracer):
        values = np.asarray(q, dtype=float)
        if not np.all(np.isfinite(values)):
            bad = np.flatnonzero(~np.isfinite(values)).tolist()
            raise ValueError(f"configuration q has non-finite entries at indices {bad}")
        norm = float(np.linalg.norm(values[3:7]))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise ValueError(
                f"the base quaternion q[3:7] = {values[3:7].tolist()} has norm {norm:.6g}, not 1 (x, y, z, w): "
                "divide it by its norm"
            )
    return q


def check_velocity(model, nu):
    """Return ν as an array after checking its shape (6 + n,); raises ValueError."""
    nu = jnp.asarray(nu)
    _check_real(nu, "velocity ν")
    if nu.shape != (model.nv,):
        raise ValueError(
            f"velocity ν must have shape ({model.nv},) = 3 linear + 3 angular (world frame) "
            f"+ {model.n_joints} joints of {model.name!r}, got {nu.shape}"
        )
    return nu


def make_configuration(base_position, base_quaternion, joint_positions):
    """q = (p (3,), ρ (4,) as x, y, z, w, s (n,)) → (7 + n,)."""
    return jnp.concatenate(
        [jnp.asarray(base_position), jnp.asarray(base_quaternion), jnp.asarray(joint_positions)]
    )


def split_configuration(q):
    """(7 + n,) → base position (3,), base quaternion (4,), joint positions (n,)."""
    return q[:3], q[3:7], q[7:]


def neutral_configuration(model):
    """Base at the origin, identity orientation, joints at 0 (clipped into their limits)."""
    s = jnp.clip(jnp.zeros(model.n_joints), model.position_limits[:, 0], model.position_limits[:, 1])
    return make_configuration(jnp.zeros(3), jnp.array([0.0, 0.0, 0.0, 1.0]), s)


def configuration_derivative(q, nu):
    """q̇ of a velocity ν: (ṗ, ½ (ω, 0) ⊗ ρ, ṡ), shapes (7 + n,), (6 + n,) → (7 + n,)."""
    omega_quaternion = jnp.concatenate([nu[3:6], jnp.zeros(1)])
    rho_dot = 0.5 * so3.quaternion_multiply(omega_quaternion, q[3:7])
    return jnp.concatenate([nu[:3], rho_dot, nu[6:]])


def integrate_configuration(q, nu, dt):
    """One step of eq. (25): p + ṗΔt, Exp(ωΔt) ⊗ ρ, s + ṡΔt. Keeps ρ a unit quaternion."""
    return jnp.concatenate(
        [q[:3] + dt * nu[:3], so3.quaternion_integrate(q[3:7], nu[3:6], dt), q[7:] + dt * nu[6:]]
    )
