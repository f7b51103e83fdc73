"""The cost of eq. (32), per knot, with the weights as a pytree argument (docs/formulation.md)."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3


def _sq(x):
    return jnp.sum(jnp.square(x))


def running_cost(task, weights, knot):
    """l[k] of eq. (32) at one knot (before the Δt factor): a scalar."""
    w = weights
    s_bar = task.params.reference_configuration[7:]
    upper = np.zeros(task.layout.n_joints, bool)
    upper[list(task.upper_body_joints)] = True
    joint_rates = knot.joint_velocities
    return (
        w.com_acc * _sq(knot.com_acceleration)
        + w.com_vel * _sq(knot.com_velocity)
        + w.com_vel_xy * _sq(knot.com_velocity[:2])
        + w.ang_mom_rate * _sq(knot.angular_momentum_rate)
        + w.ang_mom * _sq(knot.angular_momentum)
        + w.joint_vel_upper * _sq(jnp.where(upper, joint_rates, 0.0))
        + w.joint_vel_lower * _sq(jnp.where(upper, 0.0, joint_rates))
        + w.posture * _sq(knot.joint_positions - s_bar)
        + w.force * _sq(knot.contact_forces)
        + w.force_rate * _sq(knot.contact_force_rates)
        + w.thrust * _sq(knot.thrust)
        + w.throttle * _sq(knot.throttle)
        + w.base_orientation * _sq(knot.base_quaternion - jnp.array([0.0, 0.0, 0.0, 1.0]))
    )


def final_cost(task, weights, knot):
    """l_N: equilibrium at the last knot (final momentum, thrust, posture and force terms)."""
    w = weights
    s_bar = task.params.reference_configuration[7:]
    momentum = _sq(knot.com_velocity) + _sq(knot.com_acceleration) + _sq(knot.angular_momentum) + _sq(
        knot.angular_momentum_rate
    )
    return (
        w.final_momentum * momentum
        + w.final_thrust * _sq(knot.thrust)
        + w.final_posture * _sq(knot.joint_positions - s_bar)
        + w.final_force * _sq(knot.contact_forces)
    )


def initial_cost(task, weights, knot):
    """l_0: posture, base orientation (through the SO(3) log) and forces at the first knot."""
    w = weights
    reference = task.params.reference_configuration
    rho = knot.base_quaternion / jnp.linalg.norm(knot.base_quaternion)
    error = so3.quaternion_log(so3.quaternion_multiply(so3.quaternion_conjugate(reference[3:7]), rho))
    return (
        w.initial_posture * _sq(knot.joint_positions - reference[7:])
        + w.initial_base_orientation * _sq(error)
        + w.initial_force * _sq(knot.contact_forces)
    )


def slack_cost(task, weights, knot):
    """Complementarity slack penalty at one knot: w_ε Σ ε (published) + w_ε² Σ ε² (the text)."""
    slacks = jnp.concatenate([knot.normal_slack, knot.tangential_slack])
    return weights.complementarity_slack * jnp.sum(slacks) + weights.complementarity_slack_squared * _sq(slacks)


def knot_cost(task, weights, knot, total_time, role):
    """Cost contribution of one knot; role = (running, initial, final) as 0/1 floats.

    Summed over the knots, this is J of eq. (32) without the total-time term.
    """
    running, initial, final = role
    dt = total_time / task.n_intervals
    return (
        running * dt * running_cost(task, weights, knot)
        + initial * initial_cost(task, weights, knot)
        + final * final_cost(task, weights, knot)
        + slack_cost(task, weights, knot)
    )


def knot_roles(n_knots):
    """(N + 1, 3) static roles: running for k < N, initial at k = 0, final at k = N."""
    roles = np.zeros((n_knots, 3))
    roles[:-1, 0] = 1.0
    roles[0, 1] = 1.0
    roles[-1, 2] = 1.0
    return roles


def cost_terms(task, trajectory, weights=None):
    """J split into its named terms, and their sum: {running, final, initial, slack, horizon, total}."""
    weights = task.weights if weights is None else weights
    knots = trajectory.knots
    dt = trajectory.total_time / task.n_intervals
    per_knot = lambda f: jax.vmap(f, in_axes=(None, None, 0))(task, weights, knots)  # noqa: E731
    terms = dict(
        running=dt * jnp.sum(per_knot(running_cost)[:-1]),
        final=final_cost(task, weights, jax.tree.map(lambda x: x[-1], knots)),
        initial=initial_cost(task, weights, jax.tree.map(lambda x: x[0], knots)),
        slack=jnp.sum(per_knot(slack_cost)),
        horizon=weights.horizon * trajectory.total_time,
    )
    terms["total"] = sum(terms.values())
    return terms


def total_cost(task, trajectory, weights=None):
    """J of eq. (32), summed knot by knot through ``knot_cost`` (a scalar)."""
    weights = task.weights if weights is None else weights
    roles = jnp.asarray(knot_roles(task.n_knots))
    per_knot = jax.vmap(knot_cost, in_axes=(None, None, 0, None, 0))(
        task, weights, trajectory.knots, trajectory.total_time, roles
    )
    return jnp.sum(per_knot) + weights.horizon * trajectory.total_time
