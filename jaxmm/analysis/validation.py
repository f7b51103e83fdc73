"""Is a trajectory a solution? ``validate`` checks it against the physics, not the solver.

Every constraint family and box within tolerance, the CoM at its targets, no force on a corner
that is off the ground, thrust and throttle in range, and a re-simulation of the centroidal
dynamics (eq. 13, 24) from the forces and thrusts alone that must reproduce the CoM trajectory.
Beyond the paper's NLP, the joint torques the plan needs (``torques``) are reported against the
motors' effort limits, and required to be within them on request.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body.centroidal import total_mass
from jaxmm.rigid_body.kinematics import frame_poses
from jaxmm.physics.jets import thrust_forces
from jaxmm.analysis.torques import TorqueReport, joint_torques
from jaxmm.transcription import constraints


@dataclasses.dataclass(frozen=True)
class Check:
    """One test of a trajectory: the measured value against its limit (value ≤ limit passes).
    A check that is not ``enforced`` is reported but does not decide ``ValidationReport.ok``."""

    name: str
    value: float
    limit: float
    detail: str = ""
    enforced: bool = True

    @property
    def passed(self):
        return bool(np.isfinite(self.value) and self.value <= self.limit)


@dataclasses.dataclass(frozen=True)
class ValidationReport:
    """The checks of ``validate`` and what was measured on the way."""

    checks: tuple
    flight_knots: tuple  # knots at which every contact corner is off the ground
    resimulated_com: np.ndarray  # (N + 1, 3) [m]
    torques: TorqueReport  # the joint torques along the plan and the base residual

    @property
    def ok(self):
        return all(check.passed for check in self.checks if check.enforced)

    @property
    def failed(self):
        return tuple(check.name for check in self.checks if check.enforced and not check.passed)

    def __str__(self):
        width = max(len(check.name) for check in self.checks)
        lines = [f"{'check':<{width}}  {'value':>10}  {'limit':>10}  result"]
        for check in self.checks:
            verdict = "ok" if check.passed else "FAILED" if check.enforced else "over (not enforced)"
            detail = f"  ({check.detail})" if check.detail else ""
            lines.append(f"{check.name:<{width}}  {check.value:>10.3g}  {check.limit:>10.3g}  {verdict}{detail}")
        lines.append(f"flight knots: {list(self.flight_knots) or 'none'}")
        lines.append(f"joint torques: {self.torques}")
        return "\n".join(lines)


def _outside(value, lower, upper):
    return np.maximum(np.maximum(np.asarray(lower) - value, value - np.asarray(upper)), 0.0)


def check_trajectory(task, trajectory):
    """Raise a ValueError unless trajectory has the task's N + 1 knots, unbatched."""
    shape = np.shape(trajectory.knots.com)
    if shape != (task.n_knots, 3):
        raise ValueError(
            f"the trajectory must have the task's {task.n_knots} knots (leaves (N + 1, ...), not batched); "
            f"its CoM has shape {shape}"
        )


def airborne_corners(trajectory, contact_height=0.01):
    """(N + 1, nc) bool: True where a contact corner is off the ground at a knot, that is higher
    than contact_height [m]. The contact schedule of a trajectory, as ``validate`` sees it. A
    batched trajectory (leaves (B, N + 1, ...)) gives (B, N + 1, nc)."""
    return np.asarray(trajectory.knots.contact_points[..., 2]) > contact_height


def complementarity(trajectory, load=10.0):
    """How far a trajectory is from exact contact complementarity (eq. 20, 21 with ε = 0):
    {"normal": the largest f_z c_z [N m], "planar": the largest |f_z[k] (c_xy[k+1] − c_xy[k])|
    [N m], "slack": the largest slack ε_n or ε_t [N m], "slip": the largest ‖c_xy[k+1] −
    c_xy[k]‖ of a corner carrying f_z[k] ≥ ``load`` [N] [m]}. All four are 0 for a trajectory
    whose corners push only on the ground and never slide while they push; eq. 21 within σ_t
    bounds the slip by about σ_t / load. A ValueError for a load that is not a finite number ≥ 0."""
    if not (isinstance(load, (int, float, np.floating, np.integer)) and np.isfinite(load) and load >= 0):
        raise ValueError(f"complementarity's load must be a finite number of newtons ≥ 0, got {load!r}")
    knots = trajectory.knots
    force = np.asarray(knots.contact_forces[..., 2])
    points = np.asarray(knots.contact_points)
    moves = points[1:, :, :2] - points[:-1, :, :2]
    sliding = np.abs(force[:-1, :, None] * moves)
    slip = np.where(force[:-1] >= load, np.linalg.norm(moves, axis=-1), 0.0)
    slack = np.concatenate([np.ravel(knots.normal_slack), np.ravel(knots.tangential_slack)])
    return dict(normal=float(np.max(force * points[..., 2], initial=0.0)), planar=float(np.max(sliding, initial=0.0)),
                slack=float(np.max(slack, initial=0.0)), slip=float(np.max(slip, initial=0.0)))


def flight_knots(airborne):
    """The knots (a tuple of ints) at which every contact corner is off the ground, from the
    (N + 1, nc) mask of ``airborne_corners``."""
    return tuple(int(k) for k in np.flatnonzero(airborne.all(axis=1)))


def corner_groups(robot):
    """The contact corners grouped per foot (per body they are fixed to), in the order of
    ``robot.contact_frames``: ((label, (corner index, ...)), ...); the label is the corners'
    common name prefix (``l_sole`` for ``l_sole_1`` … ``l_sole_4``)."""
    model = robot.model
    groups = {}
    for index, frame in enumerate(model.frame_indices(robot.contact_frames)):
        groups.setdefault(model.topology.frame_body[frame], []).append(index)
    labelled = []
    for members in groups.values():
        names = [robot.contact_frames[i] for i in members]
        prefix = names[0]
        for name in names[1:]:
            while not name.startswith(prefix):
                prefix = prefix[:-1]
        labelled.append((prefix.rstrip("_") or names[0], tuple(members)))
    return tuple(labelled)


def resimulate_com(task, trajectory):
    """CoM trajectory re-integrated from the contact forces and thrusts alone (eq. 13, 24).

    The CoM acceleration at each knot is (Σ f_i + Σ F_j)/m + g, with F_j = −T_j R_j e_z at the
    knot's configuration; it is integrated from x[0], ẋ[0] with the task's rule (backward Euler
    for ẋ; trapezoidal or backward Euler for x). Returns (N + 1, 3) [m].
    """
    knots = trajectory.knots
    robot = task.robot
    mass = float(total_mass(robot.model))
    poses = jax.jit(jax.vmap(functools.partial(frame_poses, robot.model, frames=robot.jet_frames)))
    _, jet_rotations = poses(knots.configuration)
    jet_forces = jax.vmap(thrust_forces)(knots.thrust, jet_rotations)
    force = np.asarray(jnp.sum(knots.contact_forces, axis=1) + jnp.sum(jet_forces, axis=1))
    acceleration = force / mass + np.asarray(task.params.gravity)
    dt = float(trajectory.total_time) / task.n_intervals
    x = [np.asarray(knots.com[0])]
    v = np.asarray(knots.com_velocity[0])
    for k in range(task.n_intervals):
        v_next = v + dt * acceleration[k + 1]
        step = 0.5 * (v + v_next) if task.integration == "trapezoidal" else v_next
        x.append(x[-1] + dt * step)
        v = v_next
    return np.stack(x)


def validate(task, trajectory, *, tolerance=1e-4, contact_height=0.01, flight_force=1.0, resimulation_tolerance=0.01,
             effort_limits=None, slip_load=10.0, slip_limit=1e-3):
    """Check a trajectory against the task's physics; returns a ``ValidationReport``.

    tolerance: on every constraint family, box, target and range (physical units, as IPOPT's
    constraint-violation tolerance of the paper); contact_height [m]: a corner higher than
    this is off the ground, and then its vertical force must be ≤ flight_force [N];
    resimulation_tolerance [m]: on the re-simulated CoM; effort_limits: require every joint
    torque at knots 1..N (those whose accelerations the transcription defines) within its URDF
    effort limit, |τ| ≤ τ_max (1 + tolerance); None: where the task bounds them
    (``joint_torque_limits``). Otherwise the check is reported without deciding ``ok``, as the
    paper's NLP does not bound the torques. slip_load [N], slip_limit [m]: the largest slip
    per interval of a corner under at least slip_load (``complementarity``), reported against
    slip_limit without deciding ``ok``: the NLP bounds slip only through eq. 21's products.
    """
    checks = []
    values = jax.jit(constraints.evaluate)(task, trajectory)
    bounds = constraints.inequality_bounds(task)
    for name, value in values.items():
        value = np.asarray(value)
        violation = np.abs(value) if name not in bounds else _outside(value, *bounds[name])
        checks.append(Check(f"constraint {name}", float(violation.max(initial=0.0)), tolerance))
    lower, upper = constraints.variable_bounds(task)
    layout = task.layout
    box = _outside(np.asarray(layout.flatten(trajectory.knots)), layout.flatten(lower.knots), layout.flatten(upper.knots))
    worst = np.unravel_index(np.argmax(box), box.shape) if box.size else (0, 0)
    field = next((n for n, s in layout.slices().items() if s.start <= worst[1] < s.stop), "")
    checks.append(Check("variable boxes", float(box.max(initial=0.0)), tolerance, f"worst: {field} at knot {worst[0]}"))
    time_violation = _outside(float(trajectory.total_time), lower.total_time, upper.total_time)
    checks.append(Check("total time bounds", float(time_violation), tolerance))

    knots, params = trajectory.knots, task.params
    com = np.asarray(knots.com)
    checks.append(Check("initial CoM at target", float(np.abs(com[0] - params.initial_com).max()), tolerance))
    checks.append(Check("final CoM at target", float(np.abs(com[-1] - params.final_com).max()), tolerance))
    if np.isfinite(float(params.mid_com_height)):
        middle = task.n_intervals // 2
        checks.append(Check("mid-horizon CoM height", float(max(params.mid_com_height - com[middle, 2], 0.0)), tolerance))

    vertical = np.asarray(knots.contact_forces[..., 2])
    airborne = airborne_corners(trajectory, contact_height)
    force_in_air = float(np.where(airborne, np.abs(vertical), 0.0).max(initial=0.0))
    checks.append(Check("no force on corners off the ground", force_in_air, flight_force,
                        f"corners above {contact_height} m; max slack ε_n {float(np.max(knots.normal_slack, initial=0.0)):.3g}"))
    checks.append(Check("slip of loaded corners", complementarity(trajectory, slip_load)["slip"], slip_limit,
                        f"metres per interval, corners under ≥ {slip_load:g} N", enforced=False))
    if layout.n_jets:
        thrust = np.asarray(knots.thrust)
        throttle = np.asarray(knots.throttle)
        checks.append(Check("thrust within [0, T_max]", float(_outside(thrust, 0.0, params.max_thrust).max()), tolerance))
        checks.append(Check("throttle within range", float(_outside(throttle, *params.throttle_range).max()), tolerance))

    resimulated = resimulate_com(task, trajectory)
    checks.append(Check("re-simulated CoM", float(np.abs(resimulated - com).max()), resimulation_tolerance, "metres"))
    torques = joint_torques(task, trajectory)
    load = torques.load[1:]
    knot, joint = np.unravel_index(np.argmax(load), load.shape)
    checks.append(Check("joint torques within effort limits", float(load[knot, joint]), 1.0 + tolerance,
                        f"|τ|/τ_max at knots 1..N; worst: {torques.joint_names[joint]} at knot {knot + 1}, "
                        f"{torques.torques[knot + 1, joint]:.3g} N m against {torques.effort_limits[joint]:.3g} N m",
                        enforced=task.joint_torque_limits if effort_limits is None else bool(effort_limits)))
    return ValidationReport(checks=tuple(checks), flight_knots=flight_knots(airborne), resimulated_com=resimulated,
                            torques=torques)
