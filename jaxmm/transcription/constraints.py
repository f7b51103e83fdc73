"""The constraints of eq. (33), written once per knot (path) or per interval (transition)
and vmapped over the horizon. Families and row orders follow docs/formulation.md."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3
from jaxmm.rigid_body.centroidal import total_mass
from jaxmm.rigid_body.centroidal_derivatives import centroidal_kinematics
from jaxmm.physics.centroidal_dynamics import momentum_rate
from jaxmm.physics.contacts import friction_cone, normal_complementarity, planar_complementarity
from jaxmm.physics.jets import thrust_acceleration, thrust_forces
from jaxmm.transcription.variables import Trajectory
from jaxmm.transcription.whole_body import generalised_forces

PATH_EQUALITIES = ("centroidal_dynamics", "com", "angular_momentum", "contact_points", "jet_dynamics")
TRANSITION_EQUALITIES = (
    "com_integration", "com_velocity_integration", "angular_momentum_integration",
    "base_position_integration", "base_quaternion_integration", "joint_integration",
    "force_integration", "thrust_integration", "thrust_rate_integration",
)
PATH_INEQUALITIES = ("friction_cone", "normal_complementarity", "corner_com", "jet_com")
TRANSITION_INEQUALITIES = ("planar_complementarity",)
COMPLEMENTARITY = ("normal_complementarity", "planar_complementarity")  # eq. (20, 21)
# Beyond the paper: |τ_j| ≤ τ_max,j at knots 1..N, where the task asks for it.
JOINT_TORQUE = "joint_torque"

_Q = ("base_position", "base_quaternion", "joint_positions")
_NU = ("base_linear_velocity", "base_angular_velocity", "joint_velocities")
# The knot fields each family can depend on: (at knot k, at knot k + 1). This is the sparsity
# of the Jacobians that the solver's Gram products exploit; it covers both integration rules
# (the trapezoidal one adds the derivative at k) and is checked against the Jacobians in tests.
FAMILY_FIELDS = dict(
    centroidal_dynamics=(("com", "com_acceleration", "angular_momentum_rate", "contact_forces", "contact_points",
                          "thrust") + _Q, ()),
    com=(("com",) + _Q, ()),
    angular_momentum=(("angular_momentum",) + _Q + _NU, ()),
    contact_points=(("contact_points",) + _Q, ()),
    jet_dynamics=(("thrust", "thrust_rate", "thrust_acceleration", "throttle"), ()),
    com_integration=(("com", "com_velocity"), ("com", "com_velocity")),
    com_velocity_integration=(("com_velocity",), ("com_velocity", "com_acceleration")),
    angular_momentum_integration=(("angular_momentum",), ("angular_momentum", "angular_momentum_rate")),
    base_position_integration=(("base_position",), ("base_position", "base_linear_velocity")),
    base_quaternion_integration=(("base_quaternion",), ("base_quaternion", "base_angular_velocity")),
    joint_integration=(("joint_positions",), ("joint_positions", "joint_velocities")),
    force_integration=(("contact_forces",), ("contact_forces", "contact_force_rates")),
    thrust_integration=(("thrust",), ("thrust", "thrust_rate")),
    thrust_rate_integration=(("thrust_rate", "thrust_acceleration"), ("thrust_rate", "thrust_acceleration")),
    friction_cone=(("contact_forces",), ()),
    normal_complementarity=(("contact_forces", "contact_points", "normal_slack"), ()),
    corner_com=(("contact_points", "com"), ()),
    jet_com=(("com",) + _Q, ()),
    planar_complementarity=(("contact_forces", "contact_points", "tangential_slack"), ("contact_points",)),
    joint_torque=(_NU, _Q + _NU + ("contact_forces", "thrust")),
)


def transition_inequality_families(task):
    """The transition inequality families of the task, in row order: the planar complementarity,
    then the joint torques where ``task.joint_torque_limits`` asks for them."""
    return TRANSITION_INEQUALITIES + ((JOINT_TORQUE,) if task.joint_torque_limits else ())


def knot_kinematics(task, configuration):
    """CoM, CMM and the poses of the contact corners and jets at q (``centroidal_kinematics``)."""
    robot = task.robot
    return centroidal_kinematics(robot.model, configuration, robot.contact_frames + robot.jet_frames)


def _kinematics(task, knot, kinematics):
    """Named kinematic quantities of the knot; ``kinematics`` (from ``knot_kinematics``) if given."""
    kin = knot_kinematics(task, knot.configuration) if kinematics is None else kinematics
    nc = len(task.robot.contact_frames)
    return dict(
        corner_positions=kin["frame_positions"][:nc],
        jet_positions=kin["frame_positions"][nc:],
        jet_rotations=kin["frame_rotations"][nc:],
        com=kin["com"],
        cmm=kin["cmm"],
    )


def path_equalities(task, knot, total_time, kinematics=None):
    """Equalities at one knot (eq. 8, 14-17, 23): {family: (rows,)}, zero when satisfied.

    kinematics: ``knot_kinematics`` of the knot, if already known (or linearised).
    """
    del total_time
    params = task.params
    kin = _kinematics(task, knot, kinematics)
    mass = total_mass(task.robot.model)
    jet_forces = thrust_forces(knot.thrust, kin["jet_rotations"])
    rate = momentum_rate(
        mass, knot.com, knot.contact_forces, knot.contact_points, jet_forces, kin["jet_positions"], params.gravity
    )
    return dict(
        centroidal_dynamics=jnp.concatenate([mass * knot.com_acceleration, knot.angular_momentum_rate]) - rate,
        com=knot.com - kin["com"],
        angular_momentum=knot.angular_momentum - kin["cmm"][3:] @ knot.velocity,
        contact_points=(knot.contact_points - kin["corner_positions"]).reshape(-1),
        jet_dynamics=knot.thrust_acceleration
        - thrust_acceleration(knot.thrust, knot.thrust_rate, knot.throttle, params.jet_coefficients),
    )


def transition_equalities(task, knot, next_knot, total_time):
    """Integration from knot k to k+1 (eq. 24-27): {family: (rows,)}, zero when satisfied."""
    dt = total_time / task.n_intervals
    now, nxt = knot, next_knot
    trapezoidal = task.integration == "trapezoidal"

    def euler(value, derivative):
        return getattr(nxt, value) - getattr(now, value) - dt * getattr(nxt, derivative)

    def rule(value, derivative):
        if trapezoidal:
            mean = 0.5 * (getattr(now, derivative) + getattr(nxt, derivative))
            return getattr(nxt, value) - getattr(now, value) - dt * mean
        return euler(value, derivative)

    return dict(
        com_integration=rule("com", "com_velocity"),
        com_velocity_integration=euler("com_velocity", "com_acceleration"),
        angular_momentum_integration=euler("angular_momentum", "angular_momentum_rate"),
        base_position_integration=euler("base_position", "base_linear_velocity"),
        base_quaternion_integration=nxt.base_quaternion
        - so3.quaternion_integrate(now.base_quaternion, nxt.base_angular_velocity, dt),
        joint_integration=euler("joint_positions", "joint_velocities"),
        force_integration=(nxt.contact_forces - now.contact_forces - dt * nxt.contact_force_rates).reshape(-1),
        thrust_integration=euler("thrust", "thrust_rate"),
        thrust_rate_integration=rule("thrust_rate", "thrust_acceleration"),
    )


def path_inequalities(task, knot, total_time, kinematics=None):
    """Inequalities at one knot (eq. 12, 19, 20, boxes of eq. 29): {family: (rows,)}."""
    del total_time
    kin = _kinematics(task, knot, kinematics)
    return dict(
        friction_cone=friction_cone(knot.contact_forces, task.params.friction_coefficient),
        normal_complementarity=normal_complementarity(knot.contact_forces, knot.contact_points, knot.normal_slack),
        corner_com=(knot.contact_points - knot.com).reshape(-1),
        jet_com=(kin["jet_positions"] - knot.com).reshape(-1),
    )


def transition_inequalities(task, knot, next_knot, total_time):
    """Planar complementarity between knots k and k+1 (eq. 21): {family: (4 nc,)}; with
    ``task.joint_torque_limits``, the joint torques (n,) [N m] at knot k+1 too: inverse dynamics
    at (q, ν)[k+1] with ν̇ = (ν[k+1] − ν[k]) / Δt (backward Euler, the rule of eq. 24 and of the
    positions' integration rows), under knot k+1's contact forces and thrusts."""
    upper, lower = planar_complementarity(
        knot.contact_forces, knot.contact_points, next_knot.contact_points, knot.tangential_slack
    )
    out = dict(planar_complementarity=jnp.concatenate([upper, lower]))
    if task.joint_torque_limits:
        rate = (next_knot.velocity - knot.velocity) * (task.n_intervals / total_time)
        out[JOINT_TORQUE] = generalised_forces(task.robot, next_knot.configuration, next_knot.velocity, rate,
                                               next_knot.contact_forces, next_knot.thrust, task.params.gravity)[6:]
    return out


def inequality_bounds(task):
    """{family: (lower (rows,), upper (rows,))} of every inequality family (same at every knot)."""
    nc, nj = len(task.robot.contact_frames), len(task.robot.jet_frames)
    corner = jnp.tile(task.params.corner_com_bound, nc)
    jet = jnp.full(3 * nj, 1.0) * task.params.jet_com_bound
    sigma = jnp.full(nc, 1.0) * task.params.complementarity_tolerance  # σ_n of eq. (20)
    sigma_t = jnp.full(2 * nc, 1.0) * task.params.planar_tolerance  # σ_t of eq. (21)
    inf = jnp.inf
    effort = task.robot.model.effort_limits
    return dict(
        joint_torque=(-effort, effort),
        friction_cone=(jnp.full(4 * nc, -inf), jnp.zeros(4 * nc)),
        normal_complementarity=(jnp.full(nc, -inf), sigma),
        corner_com=(-corner, corner),
        jet_com=(-jet, jet),
        planar_complementarity=(
            jnp.concatenate([jnp.full(2 * nc, -inf), -sigma_t]),
            jnp.concatenate([sigma_t, jnp.full(2 * nc, inf)]),
        ),
    )


def evaluate(task, trajectory):
    """Every constraint family over the horizon: path families (N + 1, rows), transition
    families (N, rows)."""
    knots, total_time = trajectory.knots, trajectory.total_time
    now = jax.tree.map(lambda x: x[:-1], knots)
    nxt = jax.tree.map(lambda x: x[1:], knots)
    out = {}
    for function in (path_equalities, path_inequalities):
        out.update(jax.vmap(function, in_axes=(None, 0, None))(task, knots, total_time))
    for function in (transition_equalities, transition_inequalities):
        out.update(jax.vmap(function, in_axes=(None, 0, 0, None))(task, now, nxt, total_time))
    return out


def _spread(value, columns, size):
    """A scalar, or one value per column of ``columns`` (static, consecutive), as a row of
    ``size`` entries with the values at those columns (zeros elsewhere)."""
    value = jnp.asarray(value, dtype=float)
    if value.ndim == 0:
        return value
    if not np.all(np.diff(columns) == 1):
        raise ValueError("a box with one value per column needs consecutive columns")
    return jnp.pad(value, (int(columns[0]), size - int(columns[-1]) - 1))


def variable_bounds(task):
    """Boxes on the variables, knot by knot (docs/formulation.md, "Variable boxes").

    Returns (lower, upper) as ``Trajectory``s of the task's shape, physical units; the
    knot-dependent entries impose the boundary conditions of eq. (30, 31) and the
    mid-horizon height. Traceable: the bounds are differentiable in the task's numbers.
    """
    p = task.params
    layout = task.layout
    slices = layout.slices()
    shape = (task.n_knots, layout.size)
    bounds = [jnp.full(shape, -jnp.inf), jnp.full(shape, jnp.inf)]

    def box(field, lower, upper, knots=slice(None), entries=slice(None)):
        # Element-wise selections over static masks, which XLA fuses into a few kernels (an
        # indexed update per box compiled a scatter kernel each).
        columns = np.arange(slices[field].start, slices[field].stop)[entries]
        if not columns.size:
            return
        mask = np.zeros(shape, bool)
        mask[np.arange(shape[0])[knots], columns[:, None]] = True
        for side, value in ((0, lower), (1, upper)):
            if value is not None:
                bounds[side] = jnp.where(mask, _spread(value, columns, shape[1]), bounds[side])

    tol = p.boundary_tolerance
    xy = p.com_xy_limit
    box("com", jnp.stack([-xy, -xy, 0.0]), jnp.stack([xy, xy, jnp.inf]))
    box("com", p.initial_com, p.initial_com, knots=0)
    box("com", p.final_com, p.final_com, knots=-1)
    box("com", jnp.maximum(p.mid_com_height, 0.0), None, knots=task.n_intervals // 2, entries=slice(2, 3))
    for field in ("com_velocity", "com_acceleration", "angular_momentum", "angular_momentum_rate"):
        box(field, -tol, tol, knots=0)
    box("base_quaternion", -1.0, 1.0)
    reference = p.reference_configuration[3:7]
    box("base_quaternion", jnp.maximum(reference - tol, -1), jnp.minimum(reference + tol, 1), knots=0)
    identity = jnp.array([0.0, 0.0, 0.0, 1.0])
    final_tol = p.final_orientation_tolerance
    box("base_quaternion", jnp.maximum(identity - final_tol, -1), jnp.minimum(identity + final_tol, 1), knots=-1)
    box("joint_positions", p.joint_limits[:, 0], p.joint_limits[:, 1])
    box("base_linear_velocity", -p.base_linear_velocity_limit, p.base_linear_velocity_limit)
    box("base_angular_velocity", -p.base_angular_velocity_limit, p.base_angular_velocity_limit)
    box("joint_velocities", -p.joint_velocity_limit, p.joint_velocity_limit)
    vertical = slice(2, None, 3)
    box("contact_forces", 0.0, None, entries=vertical)
    box("contact_points", 0.0, None, entries=vertical)
    box("contact_points", 0.0, 0.0, knots=0, entries=vertical)
    # f[k+1] integrates ḟ[k+1] (force_integration): ḟ[0] enters no constraint, and only its cost,
    # minimal at 0, if any. Left free it made the Newton matrix singular on walk-to-fly (no ḟ
    # weight), so that every iteration needed an inertia correction that damped the whole step.
    box("contact_force_rates", 0.0, 0.0, knots=0)
    box("thrust", 0.0, p.max_thrust)
    if task.zero_initial_thrust:
        box("thrust", 0.0, tol, knots=0)
        box("thrust_rate", -tol, tol, knots=0)
    box("throttle", p.throttle_range[0], p.throttle_range[1])
    box("normal_slack", 0.0, p.slack_limit)
    box("tangential_slack", 0.0, p.slack_limit)
    N = task.n_intervals
    return (
        Trajectory(layout.unflatten(bounds[0]), N * p.min_dt),
        Trajectory(layout.unflatten(bounds[1]), N * p.max_dt),
    )
