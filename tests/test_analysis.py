"""``validate`` passes a physically exact trajectory, names what is wrong with bad ones, and its
thresholds decide where a measured value turns a check from passed to failed."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm
from jaxmm import analysis, tasks
from jaxmm.transcription.variables import Trajectory


def _standing_still(knots=6):
    """iRonCub standing still with idle jets: an exact solution of its own task.

    Contact forces: the minimum-norm set with Σ f = −m g and Σ (c − x) × f = 0; throttle: the
    idle value where the jet model (eq. 8) gives T̈ = 0 at T = Ṫ = 0.
    """
    robot = jaxmm.load_ironcub()
    q = robot.standing_configuration
    com = np.asarray(jaxmm.com_position(robot.model, q))
    task = tasks.scenario("take_off", knots=knots, initial_com=com, final_com=com, final_orientation_tolerance=0.02)
    corners = np.asarray(jaxmm.frame_poses(robot.model, q, robot.contact_frames)[0])
    mass = float(jaxmm.total_mass(robot.model))
    # 6 equations in the 24 force components.
    A = np.zeros((6, 24))
    for i, c in enumerate(corners):
        A[:3, 3 * i : 3 * i + 3] = np.eye(3)
        A[3:, 3 * i : 3 * i + 3] = np.asarray(jaxmm.rigid_body.so3.skew(c - com))
    b = np.concatenate([-mass * np.asarray(task.params.gravity), np.zeros(3)])
    forces = np.linalg.lstsq(A, b, rcond=None)[0].reshape(8, 3)
    idle = []
    for k_t, k_tt, k_d, k_dd, k_td, b_u, b_t, b_d, b_uu, c in np.asarray(task.params.jet_coefficients):
        roots = np.roots([b_u * b_uu, b_u, c])
        idle.append(min(r.real for r in roots if abs(r.imag) < 1e-12 and 0 <= r.real <= 100))
    n_knots = task.n_knots
    zeros = task.layout.unflatten(jnp.zeros((n_knots, task.layout.size)))
    repeat = lambda x: jnp.broadcast_to(jnp.asarray(x), (n_knots,) + np.shape(x))  # noqa: E731
    knots = dataclasses.replace(
        zeros,
        com=repeat(com),
        base_position=repeat(q[:3]),
        base_quaternion=repeat(q[3:7]),
        joint_positions=repeat(q[7:]),
        contact_forces=repeat(forces),
        contact_points=repeat(corners),
        throttle=repeat(np.array(idle)),
    )
    return task, Trajectory(knots, jnp.asarray(task.n_intervals * 0.1))


def test_an_exact_standing_trajectory_passes():
    task, trajectory = _standing_still()
    report = analysis.validate(task, trajectory)
    assert report.ok, str(report)
    assert report.flight_knots == ()
    assert np.abs(report.resimulated_com - np.asarray(trajectory.knots.com)).max() < 1e-9
    assert np.all(np.asarray(trajectory.knots.contact_forces[..., 2]) > 0)  # a genuine stance


def test_the_initial_guess_fails_where_it_should():
    task = tasks.scenario("take_off", knots=10)
    report = analysis.validate(task, tasks.initial_guess(task))
    assert not report.ok
    for name in ("constraint centroidal_dynamics", "constraint com", "constraint jet_dynamics", "re-simulated CoM"):
        assert name in report.failed, str(report)
    assert "constraint contact_points" not in report.failed
    assert "FAILED" in str(report)


def test_a_pushing_foot_in_the_air_is_caught():
    task, trajectory = _standing_still()
    lifted = trajectory.knots.contact_points.at[3, 0, 2].set(0.05)
    report = analysis.validate(task, Trajectory(dataclasses.replace(trajectory.knots, contact_points=lifted), trajectory.total_time))
    assert "no force on corners off the ground" in report.failed
    assert "constraint contact_points" in report.failed
    assert "constraint normal_complementarity" in report.failed


def test_complementarity_measures_the_products_of_eq_20_and_21():
    """Zero for a stance (its corners are where the kinematics put them, within 1e-6 m of the
    ground); a lifted corner's f_z c_z, a pushing corner's sliding |f_z Δc_xy| and the largest
    slack, each where it was put."""
    task, trajectory = _standing_still()
    knots = trajectory.knots
    still = analysis.complementarity(trajectory)
    assert still["normal"] < 1e-4 and still["planar"] == 0.0 and still["slack"] == 0.0
    force = float(knots.contact_forces[3, 0, 2])
    moved = dataclasses.replace(
        knots, contact_points=knots.contact_points.at[3, 0, 2].set(0.05).at[2, 1, 0].add(-0.002),
        tangential_slack=knots.tangential_slack.at[4, 2].set(3e-3))
    measure = analysis.complementarity(Trajectory(moved, trajectory.total_time))
    sliding = max(float(knots.contact_forces[1, 1, 2]), float(knots.contact_forces[2, 1, 2])) * 0.002
    assert measure["normal"] == pytest.approx(0.05 * force, abs=still["normal"])
    assert measure["planar"] == pytest.approx(sliding, rel=1e-9) and measure["slack"] == 3e-3
    # The 2 mm move is a slip under the stance's load, not under a load above every force.
    assert still["slip"] == 0.0 and measure["slip"] == pytest.approx(0.002, rel=1e-9)
    above = 1.0 + float(knots.contact_forces[..., 2].max())
    assert analysis.complementarity(Trajectory(moved, trajectory.total_time), load=above)["slip"] == 0.0
    report = analysis.validate(task, Trajectory(moved, trajectory.total_time), slip_limit=1e-3)
    slip = next(c for c in report.checks if c.name == "slip of loaded corners")
    assert slip.value == pytest.approx(0.002, rel=1e-9) and not slip.passed and not slip.enforced


@pytest.mark.parametrize("load", [-1.0, float("nan"), float("inf"), "10"])
def test_complementarity_refuses_a_load_that_is_not_a_force(load):
    _, trajectory = _standing_still()
    with pytest.raises(ValueError, match="load"):
        analysis.complementarity(trajectory, load=load)


def test_unbalanced_forces_fail_the_resimulation():
    task, trajectory = _standing_still()
    weaker = trajectory.knots.contact_forces * 0.9
    report = analysis.validate(task, Trajectory(dataclasses.replace(trajectory.knots, contact_forces=weaker), trajectory.total_time))
    assert "re-simulated CoM" in report.failed
    assert "constraint centroidal_dynamics" in report.failed
    assert report.resimulated_com[-1, 2] < trajectory.knots.com[-1, 2] - 0.01  # it falls


def test_the_resimulation_tolerance_decides_its_verdict():
    """With every contact force 10 % short and no thrust, the re-simulated CoM sinks from rest
    at 0.1 |g|; the trapezoidal rule of ``resimulate_com`` integrates a constant acceleration
    exactly, so it ends 0.1 |g| T²/2 below the planned, still CoM. A tolerance 1 % above that
    passes the check, one 1 % below fails it: the same trajectory, two verdicts."""
    task, trajectory = _standing_still()
    assert task.integration == "trapezoidal" and not np.any(np.asarray(trajectory.knots.thrust))
    weaker = Trajectory(dataclasses.replace(trajectory.knots, contact_forces=trajectory.knots.contact_forces * 0.9),
                        trajectory.total_time)
    drop = 0.1 * np.linalg.norm(task.params.gravity) * float(trajectory.total_time) ** 2 / 2
    for tolerance, fails in ((0.99 * drop, True), (1.01 * drop, False)):
        report = analysis.validate(task, weaker, resimulation_tolerance=tolerance)
        assert ("re-simulated CoM" in report.failed) == fails, str(report)


def test_contact_height_and_flight_force_decide_their_verdict():
    """One corner raised 3 cm at a knot, still pushing with its stance force f: under a
    contact_height just above 3 cm it is on the ground and its force allowed; just below, it
    is off the ground, and its force fails the check under a flight_force just below f and
    passes it just above f."""
    task, trajectory = _standing_still()
    height = 0.03
    raised = Trajectory(dataclasses.replace(trajectory.knots, contact_points=trajectory.knots.contact_points.at[
        3, 0, 2].set(height)), trajectory.total_time)
    force = float(trajectory.knots.contact_forces[3, 0, 2])
    assert force > 1.0  # the default flight_force: the check has a force to refuse

    def in_air_fails(**thresholds):
        return "no force on corners off the ground" in analysis.validate(task, raised, **thresholds).failed

    assert not in_air_fails(contact_height=1.01 * height) and in_air_fails(contact_height=0.99 * height)
    assert in_air_fails(contact_height=0.99 * height, flight_force=0.99 * force)
    assert not in_air_fails(contact_height=0.99 * height, flight_force=1.01 * force)


def test_torques_of_a_stance_balance_gravity_through_the_jacobians():
    """Standing still, the base residual vanishes (the contact forces balance gravity about the
    CoM) and the joint torques equal the static ones from the CoM and corner Jacobians alone,
    τ_s = −m J_com,sᵀ g − Σ_i J_i,sᵀ f_i, an identity independent of the recursive algorithm."""
    task, trajectory = _standing_still()
    robot, q = task.robot, np.asarray(trajectory.knots.configuration[0])
    torques = analysis.joint_torques(task, trajectory)
    assert torques.torques.shape == (task.n_knots, robot.model.n_joints)
    assert np.abs(torques.base_force).max() < 1e-9 and np.abs(torques.base_torque).max() < 1e-9
    mass = float(jaxmm.total_mass(robot.model))
    static = -mass * np.asarray(jaxmm.com_jacobian(robot.model, q))[:, 6:].T @ np.asarray(task.params.gravity)
    for frame, force in zip(robot.contact_frames, np.asarray(trajectory.knots.contact_forces[0])):
        static -= np.asarray(jaxmm.frame_jacobian(robot.model, q, frame))[:3, 6:].T @ force
    assert np.abs(torques.torques - static).max() < 1e-9 * np.abs(static).max()
    assert np.abs(static).max() > 1.0  # the legs carry the robot: the identity is not 0 = 0


def test_effort_limits_are_reported_and_enforced_on_request():
    """The stance needs torques within iRonCub's motors; with the limits cut below the largest
    load the check turns over: reported without deciding ``ok`` by default, failed with
    ``effort_limits=True``, the worst joint and knot named."""
    task, trajectory = _standing_still()
    report = analysis.validate(task, trajectory, effort_limits=True)
    assert report.ok, str(report)
    name, knot, torque, limit = report.torques.worst
    assert abs(torque) <= limit
    model = task.robot.model
    weak = dataclasses.replace(task, robot=dataclasses.replace(task.robot, model=dataclasses.replace(
        model, effort_limits=model.effort_limits.at[model.joint_index(name)].set(0.5 * abs(torque)))))
    lenient = analysis.validate(weak, trajectory)
    assert lenient.ok and "over (not enforced)" in str(lenient)
    strict = analysis.validate(weak, trajectory, effort_limits=True)
    assert strict.failed == ("joint torques within effort limits",)
    assert f"{name} at knot" in str(strict) and strict.torques.saturated[name][1] == pytest.approx(2.0)


def test_knot_accelerations_follow_the_backward_euler_rule():
    """ν̇[k] = (ν[k] − ν[k−1]) / Δt, and knot 0 takes knot 1's."""
    task, trajectory = _standing_still()
    ramp = np.arange(task.n_knots, dtype=float)[:, None] * np.linspace(0.1, 1.0, task.robot.model.n_joints)
    moving = Trajectory(dataclasses.replace(trajectory.knots, joint_velocities=jnp.asarray(ramp ** 2)), trajectory.total_time)
    dt = float(trajectory.total_time) / task.n_intervals
    rates = np.asarray(analysis.knot_accelerations(task, moving))[:, 6:]
    expected = np.diff(ramp ** 2, axis=0) / dt
    assert np.allclose(rates[1:], expected, rtol=1e-12) and np.allclose(rates[0], expected[0], rtol=1e-12)
