"""Ready-made tasks: the paper's four scenarios on iRonCub, a builder for any robot, and the
published initial guess."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body.kinematics import frame_poses
from jaxmm.robots import ironcub_description, load_ironcub
from jaxmm.transcription.problem import INTEGRATION_RULES, Task, TaskParams, Weights
from jaxmm.transcription.variables import Trajectory

SLACK_PENALTIES = ("linear", "squared")
# σ_t [N m] of the exact task's planar complementarity (eq. 21): a slip of at most 10 µm per
# interval under 100 N. The smallest of the values scanned (1e-6 to 1e-3) with which the four
# published scenarios and eight variants converge from their guesses (docs/design-decisions.md,
# "The planar rows' own tolerance").
PLANAR_TOLERANCE = 1e-3

_IRONCUB_WEIGHTS = dict(
    com_acc=1e5, com_vel=1e7, ang_mom_rate=1e4, ang_mom=1e4, joint_vel_upper=5e5,
    joint_vel_lower=1e4, posture=1e6, force=5e1, force_rate=1e0, throttle=1e-1, final_thrust=1e2,
    initial_posture=1e6, initial_base_orientation=1e5, final_momentum=1e6,
    complementarity_slack=1e5,
)

# The four published scenarios (CoM in metres, world frame; the robot faces −x).
SCENARIOS = {
    "take_off": dict(
        knots=70, initial_com=(0.0, 0.0, 0.57), final_com=(0.0, 0.0, 0.80), weights=_IRONCUB_WEIGHTS,
        description="lift off from standing to a hover 23 cm higher",
    ),
    "take_off_and_landing": dict(
        knots=200, initial_com=(0.0, 0.0, 0.57), final_com=(0.0, 0.0, 0.57), mid_com_height=0.80,
        weights=_IRONCUB_WEIGHTS, description="fly above 0.80 m at mid-horizon, land where it started",
    ),
    "walk_to_fly": dict(
        knots=100, initial_com=(0.0, 0.0, 0.57), final_com=(-0.9, 0.0, 0.70),
        weights=dict(
            com_acc=1e5, com_vel=1e7, ang_mom_rate=1e4, ang_mom=1e4, joint_vel_upper=5e5,
            joint_vel_lower=1e5, posture=1e7, force=1e0, thrust=2e3, base_orientation=1e7,
            initial_posture=1e6, initial_base_orientation=1e5, initial_force=1e1,
            final_momentum=1e6, complementarity_slack=1e7,
        ),
        description="walk 0.9 m forward while the thrust grows, then fly",
    ),
    "jumping": dict(
        knots=60, initial_com=(0.0, 0.0, 0.57), final_com=(-0.1, 0.0, 0.57), mid_com_height=0.70,
        jets=False, corner_com_bound=(0.3, 0.4, 0.6), final_orientation_tolerance=1e-2,
        zero_initial_thrust=False,
        weights=dict(
            com_acc=1e0, com_vel_xy=1e0, ang_mom_rate=1e0, ang_mom=1e0, joint_vel_upper=1e4,
            joint_vel_lower=1e4, posture=2e1, force=1e0, force_rate=1e-1, initial_posture=1e5,
            final_posture=1e5, initial_force=1e1, final_force=1e1, final_momentum=1e6,
            horizon=1e-2, complementarity_slack=1e7,
        ),
        description="a jump with the legs only (no jets): dip, push, fly above 0.70 m, land",
    ),
}


def canonical_name(name):
    """The ``SCENARIOS`` key of a scenario name ("take-off" → "take_off"); ValueError if unknown."""
    key = name.replace("-", "_")
    if key not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; scenarios: {', '.join(SCENARIOS)}")
    return key


def _target(com, label, com_xy_limit):
    """A CoM target (3,) [m], checked to lie in the workspace: |x|, |y| ≤ com_xy_limit, z ≥ 0."""
    com = _vector(com, 3, label)
    if np.any(np.abs(com[:2]) > com_xy_limit) or com[2] < 0:
        raise ValueError(f"{label} {com.tolist()} is outside the workspace bounds (|x|, |y| ≤ {com_xy_limit} m, z ≥ 0)")
    return com


def _check_numbers(positive, non_negative, slack_limit, mid_com_height):
    """Raise ValueError naming the first of ``build_task``'s numbers out of its range: the
    ``positive`` {name: value} finite and > 0, the ``non_negative`` finite and ≥ 0, slack_limit
    ≥ 0 (inf allowed), mid_com_height finite or None."""
    for label, value in positive.items():
        if not (np.ndim(value) == 0 and np.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a finite positive number, got {value!r}")
    for label, value in non_negative.items():
        if not (np.ndim(value) == 0 and np.isfinite(value) and value >= 0):
            raise ValueError(f"{label} must be a finite non-negative number, got {value!r}")
    if not (np.ndim(slack_limit) == 0 and slack_limit >= 0):
        raise ValueError(f"slack_limit must be a non-negative number (inf: unbounded), got {slack_limit!r}")
    if mid_com_height is not None and not np.isfinite(mid_com_height):
        raise ValueError(f"mid_com_height must be finite (or None: no mid-horizon target), got {mid_com_height!r}")


def _jet_data(robot, jet_coefficients, max_thrust):
    """(jet_coefficients (nj, 10), max_thrust (nj,) [N]) checked for ``robot``'s nj jets: both
    required when it has jets, empty when it has none."""
    nj = len(robot.jet_frames)
    if not nj:
        return np.zeros((0, 10)), np.zeros(0)
    if jet_coefficients is None or max_thrust is None:
        raise ValueError(f"robot {robot.name!r} has {nj} jets: jet_coefficients (nj, 10) and max_thrust (nj,) are required")
    return _array(jet_coefficients, (nj, 10), "jet_coefficients"), _array(max_thrust, (nj,), "max_thrust")


def build_task(
    robot,
    initial_com,
    final_com,
    knots,
    weights,
    *,
    name="task",
    mid_com_height=None,
    jet_coefficients=None,
    max_thrust=None,
    throttle_range=(0.0, 100.0),
    friction_coefficient=0.33,
    corner_com_bound=(0.3, 0.3, 0.6),
    jet_com_bound=0.5,
    joint_limits=None,
    joint_velocity_limit=7.0,
    base_linear_velocity_limit=2.0,
    base_angular_velocity_limit=2.0,
    com_xy_limit=1.5,
    boundary_tolerance=1e-3,
    final_orientation_tolerance=1e-3,
    min_dt=0.05,
    max_dt=0.10,
    gravity=(0.0, 0.0, -9.81),
    complementarity_tolerance=0.0,
    planar_tolerance=None,
    slack_limit=np.inf,
    planar_relaxation=1.0,
    zero_initial_thrust=True,
    integration="trapezoidal",
    slack_penalty="linear",
    upper_body_joints=(),
    joint_torque_limits=False,
):
    """A ``Task`` for any ``Robot`` (its jet and contact frames are the robot's).

    knots: N, the number of intervals (N + 1 knots, N ≥ 2). weights: {name: value} or
    ``Weights``. jet_coefficients (nj, 10) and max_thrust (nj,) are required when the robot
    has jets. joint_limits (n, 2) [rad] default to the URDF limits. upper_body_joints: names.
    complementarity_tolerance, planar_tolerance, slack_limit: the normal and planar
    complementarity rows' σ_n, σ_t and the slacks' bound (``TaskParams``; σ_t None: σ_n; the
    defaults are the published relaxation). planar_relaxation: κ_t, the relaxation homotopy's
    share of σ on the planar rows (``TaskParams``). slack_penalty: "linear"
    (published) or "squared" (``with_slack_penalty``). joint_torque_limits: bound every
    joint torque by the URDF's effort limit (``Task.joint_torque_limits``; off in the paper's NLP).
    Raises ValueError naming the problem for inconsistent input.
    """
    model = robot.model
    nj = len(robot.jet_frames)
    planar_tolerance = complementarity_tolerance if planar_tolerance is None else planar_tolerance
    if not isinstance(knots, (int, np.integer)) or knots < 2:
        raise ValueError(f"knots must be an integer N ≥ 2 (N + 1 knots), got {knots!r}")
    if integration not in INTEGRATION_RULES:
        raise ValueError(f"integration must be one of {INTEGRATION_RULES}, got {integration!r}")
    if slack_penalty not in SLACK_PENALTIES:
        raise ValueError(f"slack_penalty must be one of {SLACK_PENALTIES}, got {slack_penalty!r}")
    initial_com, final_com = (_target(v, label, com_xy_limit) for v, label in ((initial_com, "initial_com"),
                                                                             (final_com, "final_com")))
    if not (min_dt > 0 and np.isfinite(max_dt) and max_dt >= min_dt):
        raise ValueError(f"time-step bounds must satisfy 0 < min_dt ≤ max_dt < ∞, got {min_dt}, {max_dt}")
    _check_numbers(dict(friction_coefficient=friction_coefficient, jet_com_bound=jet_com_bound,
                        joint_velocity_limit=joint_velocity_limit, base_linear_velocity_limit=base_linear_velocity_limit,
                        base_angular_velocity_limit=base_angular_velocity_limit, com_xy_limit=com_xy_limit),
                   dict(boundary_tolerance=boundary_tolerance, final_orientation_tolerance=final_orientation_tolerance,
                        complementarity_tolerance=complementarity_tolerance,
                        planar_tolerance=planar_tolerance, planar_relaxation=planar_relaxation),
                   slack_limit, mid_com_height)
    throttle = _vector(throttle_range, 2, "throttle_range")
    if not throttle[0] <= throttle[1]:
        raise ValueError(f"throttle_range must be (lower, upper) with lower ≤ upper, got {throttle.tolist()}")
    jet_coefficients, max_thrust = _jet_data(robot, jet_coefficients, max_thrust)
    if joint_limits is None:
        joint_limits = np.asarray(model.position_limits)
    joint_limits = _array(joint_limits, (model.n_joints, 2), "joint_limits")
    if not isinstance(weights, Weights):
        weights = Weights.from_dict(dict(weights))
    params = TaskParams(
        initial_com=jnp.asarray(initial_com),
        final_com=jnp.asarray(final_com),
        mid_com_height=jnp.asarray(-np.inf if mid_com_height is None else float(mid_com_height)),
        reference_configuration=jnp.asarray(robot.standing_configuration),
        friction_coefficient=jnp.asarray(float(friction_coefficient)),
        corner_com_bound=jnp.asarray(_vector(corner_com_bound, 3, "corner_com_bound")),
        jet_com_bound=jnp.asarray(float(jet_com_bound)),
        max_thrust=jnp.asarray(max_thrust),
        throttle_range=jnp.asarray(throttle),
        jet_coefficients=jnp.asarray(jet_coefficients),
        joint_limits=jnp.asarray(joint_limits),
        joint_velocity_limit=jnp.asarray(float(joint_velocity_limit)),
        base_linear_velocity_limit=jnp.asarray(float(base_linear_velocity_limit)),
        base_angular_velocity_limit=jnp.asarray(float(base_angular_velocity_limit)),
        com_xy_limit=jnp.asarray(float(com_xy_limit)),
        boundary_tolerance=jnp.asarray(float(boundary_tolerance)),
        final_orientation_tolerance=jnp.asarray(float(final_orientation_tolerance)),
        min_dt=jnp.asarray(float(min_dt)),
        max_dt=jnp.asarray(float(max_dt)),
        gravity=jnp.asarray(_vector(gravity, 3, "gravity")),
        complementarity_tolerance=jnp.asarray(float(complementarity_tolerance)),
        planar_tolerance=jnp.asarray(float(planar_tolerance)),
        slack_limit=jnp.asarray(float(slack_limit)),
        planar_relaxation=jnp.asarray(float(planar_relaxation)),
    )
    task = Task(
        robot=robot,
        params=params,
        weights=weights,
        name=name,
        n_intervals=int(knots),
        zero_initial_thrust=bool(zero_initial_thrust and nj > 0),
        integration=integration,
        upper_body_joints=tuple(model.joint_index(j) for j in upper_body_joints),
        joint_torque_limits=bool(joint_torque_limits),
    )
    return task if slack_penalty == "linear" else with_slack_penalty(task, slack_penalty)


def with_slack_penalty(task, penalty):
    """``task`` with its slack weight w on the slacks of eq. (20, 21) as w Σ ε (``"linear"``,
    the published runs: an exact penalty) or w Σ ε² (``"squared"``, the paper's text: smooth,
    so that its optimum keeps small positive slacks). w is the task's ``complementarity_slack``
    plus ``complementarity_slack_squared`` (one of them is normally zero); both penalties are
    data, so one compiled solve serves both. Raises ValueError for another ``penalty``.
    """
    if penalty not in SLACK_PENALTIES:
        raise ValueError(f"slack_penalty must be one of {SLACK_PENALTIES}, got {penalty!r}")
    w = task.weights.complementarity_slack + task.weights.complementarity_slack_squared
    zero = jnp.zeros_like(w)
    linear, squared = (w, zero) if penalty == "linear" else (zero, w)
    weights = dataclasses.replace(task.weights, complementarity_slack=linear, complementarity_slack_squared=squared)
    return dataclasses.replace(task, weights=weights)


def exact_complementarity(task, tolerance=1e-6, planar_tolerance=PLANAR_TOLERANCE):
    """``task`` with Scholtes' relaxation of the contact complementarity in place of the published
    one: f_z c_z ≤ σ_n and |f_z Δc| ≤ σ_t (eq. 20, 21) with σ_n = tolerance, σ_t =
    planar_tolerance [N m] (None: σ_n) and the slacks ε_n, ε_t fixed at 0, so that a corner c_z
    above the ground carries at most σ_n / c_z [N] and a loaded one slips at most σ_t / f_z [m] per
    interval (1e-3 N m: 10 µm under 100 N).

    σ_t is apart from σ_n because the planar rows of a foot's four corners bound its three planar
    degrees of freedom eight times over: the tighter σ_t, the nearer their gradients come to
    dependence at a stance, and the interior-point iterates then approach the answer like 1/k
    with multipliers growing without bound (docs/design-decisions.md, "The planar rows' own
    tolerance").

    Its NLP has the published one's structure (σ and the slacks' bound are data), so one compiled
    solve serves both. From the published guess solve it with the relaxation homotopy
    (``programs.EXACT_OPTIONS``: κ_σ = 1e-3, μ × 0.7 per barrier problem); warm-started from the
    published task's answer, ``solve_task(exact_complementarity(task), warm_start=relaxed)``, it
    moves an optimum that buys force on a corner in the air to a physical one nearby.
    """
    planar_tolerance = tolerance if planar_tolerance is None else planar_tolerance
    for label, value in (("tolerance", tolerance), ("planar_tolerance", planar_tolerance)):
        if not (np.ndim(value) == 0 and np.isfinite(value) and value >= 0):
            raise ValueError(f"{label} must be a finite non-negative number [N m], got {value!r}")
    params = dataclasses.replace(task.params, complementarity_tolerance=jnp.asarray(float(tolerance)),
                                 planar_tolerance=jnp.asarray(float(planar_tolerance)), slack_limit=jnp.asarray(0.0))
    return dataclasses.replace(task, params=params)


def _array(value, shape, label):
    array = np.asarray(value, dtype=float)
    if array.shape != shape:
        raise ValueError(f"{label} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{label} must be finite")
    return array


def _vector(value, size, label):
    return _array(value, (size,), label)


def scenario(name, robot=None, knots=None, keep_horizon=False, **overrides):
    """One of the four published scenarios on iRonCub, as a ``Task``.

    name: "take_off", "take_off_and_landing", "walk_to_fly" or "jumping" (hyphens allowed).
    robot: default the assembled iRonCub. knots: N (default: the published one).
    keep_horizon: with N knots other than the published N₀, scale the time-step bounds by N₀ / N
    so that the horizon range stays the published one (take-off with 14 knots: Δt in
    0.25–0.5 s). overrides: any ``build_task`` keyword (targets, weights, bounds, options); a
    ``weights`` dict is merged into the published weights.
    """
    key = canonical_name(name)
    if keep_horizon and knots is not None:
        scale = SCENARIOS[key]["knots"] / knots
        defaults = build_task.__kwdefaults__
        overrides = dict(dict(min_dt=defaults["min_dt"] * scale, max_dt=defaults["max_dt"] * scale), **overrides)
    spec = dict(SCENARIOS[key])
    spec.pop("description")
    uses_jets = spec.pop("jets", True)
    robot = load_ironcub() if robot is None else robot
    if not uses_jets:
        robot = dataclasses.replace(robot, jet_frames=())
    description = ironcub_description()
    weights = dict(spec.pop("weights"))
    weights.update(overrides.pop("weights", {}))
    arguments = dict(
        name=key,
        jet_coefficients=description["jets"]["coefficients"] if uses_jets else None,
        max_thrust=description["jets"]["max_thrust_N"] if uses_jets else None,
        throttle_range=description["jets"]["throttle_range"],
        friction_coefficient=description["contacts"]["friction_coefficient"],
        joint_limits=_planner_joint_limits(robot, description),
        joint_velocity_limit=description["planner"]["joint_velocity_limit_rad_s"],
        base_linear_velocity_limit=description["planner"]["base_linear_velocity_limit_m_s"],
        base_angular_velocity_limit=description["planner"]["base_angular_velocity_limit_rad_s"],
        upper_body_joints=[j for j in description["planner"]["upper_body_joints"] if j in robot.model.joint_names],
    )
    arguments.update(spec)
    arguments.pop("knots")
    arguments.update(overrides)
    return build_task(
        robot,
        arguments.pop("initial_com"),
        arguments.pop("final_com"),
        SCENARIOS[key]["knots"] if knots is None else knots,
        weights,
        **arguments,
    )


def with_intervals(task, n_intervals):
    """``task`` on ``n_intervals`` intervals over the same range of horizons: the time-step
    bounds (min_dt, max_dt [s]) scaled by N / n_intervals, everything else kept (a coarse
    version of a task, whose solution, resampled with ``variables.resample``, is a guess for
    the task itself; the mid-horizon height applies at the new middle knot). For a published
    scenario this is ``scenario(name, knots=n_intervals, keep_horizon=True)``."""
    if not isinstance(task, Task):
        raise TypeError(f"task must be a Task, got {type(task).__name__}")
    if isinstance(n_intervals, bool) or not isinstance(n_intervals, (int, np.integer)) or n_intervals < 2:
        raise ValueError(f"n_intervals must be an integer ≥ 2, got {n_intervals!r}")
    scale = task.n_intervals / int(n_intervals)
    params = dataclasses.replace(task.params, min_dt=task.params.min_dt * scale, max_dt=task.params.max_dt * scale)
    return dataclasses.replace(task, params=params, n_intervals=int(n_intervals))


def _planner_joint_limits(robot, description):
    planner = dict(zip(description["joints"]["optimised"], np.deg2rad(description["planner"]["joint_limits_deg"])))
    urdf = np.asarray(robot.model.position_limits)
    return np.array([planner.get(j, urdf[i]) for i, j in enumerate(robot.model.joint_names)])


@jax.jit
def initial_guess(task):
    """The published initial guess (docs/formulation.md): a ``Trajectory``. Compiled as one
    program: built op by op, its forward kinematics would compile every operation on its own
    (seconds before a first solve).

    CoM and contact-point xy interpolated linearly from x_0 to x_N; contact points start at
    the reference pose's corners; thrust 30 N; base pose and joints at the reference
    configuration; everything else 0; T_total = N · max_dt.
    """
    layout = task.layout
    n_knots = task.n_knots
    q = task.params.reference_configuration
    alpha = jnp.linspace(0.0, 1.0, n_knots)[:, None]
    shift = task.params.final_com - task.params.initial_com
    com = task.params.initial_com + alpha * shift
    corners, _ = frame_poses(task.robot.model, q, task.robot.contact_frames) if layout.n_contacts else (jnp.zeros((0, 3)), None)
    points = corners[None] + alpha[:, :, None] * jnp.concatenate([shift[:2], jnp.zeros(1)])[None, None]
    zeros = layout.unflatten(jnp.zeros((n_knots, layout.size)))
    knots = dataclasses.replace(
        zeros,
        com=com,
        base_position=jnp.broadcast_to(q[:3], (n_knots, 3)),
        base_quaternion=jnp.broadcast_to(q[3:7], (n_knots, 4)),
        joint_positions=jnp.broadcast_to(q[7:], (n_knots, layout.n_joints)),
        contact_points=points,
        thrust=jnp.full((n_knots, layout.n_jets), 30.0),
    )
    return Trajectory(knots=knots, total_time=jnp.asarray(task.n_intervals * task.params.max_dt))
