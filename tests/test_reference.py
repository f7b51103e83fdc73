"""The JAX transcription against the independent CasADi + ADAM one (jaxmm.reference), and an
IPOPT solve of take-off checked with the JAX residuals.

Needs the ``reference`` extra (casadi; adam-robotics with its CasADi backend, which imports
liecasadi). The robot is the real iRonCub URDF where ``../shared`` has it, else the assembled
default iRonCub written to a file: both sides always read the same URDF.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm
from conftest import IRONCUB_URDF
from jaxmm import tasks
from jaxmm.reference import COST_TERMS, ReferenceNLP, solve_ipopt
from jaxmm.transcription import constraints, costs
from jaxmm.transcription.variables import Trajectory

PARITY_TOLERANCE = 1e-14  # relative; the measured worst is 5.1e-15 (a cost term), 1.8e-15 for the constraints
# Standard deviation of the random perturbation of each field around the initial guess.
PERTURBATION = dict(
    com=0.1, com_velocity=1.0, com_acceleration=5.0, angular_momentum=2.0, angular_momentum_rate=10.0,
    base_position=0.1, joint_positions=0.5, base_linear_velocity=1.0, base_angular_velocity=2.0,
    joint_velocities=3.0, contact_forces=80.0, contact_force_rates=300.0, contact_points=0.1, thrust=40.0,
    thrust_rate=30.0, thrust_acceleration=50.0, throttle=30.0, normal_slack=1.0, tangential_slack=1.0,
)

_evaluate = jax.jit(constraints.evaluate)
_cost_terms = jax.jit(costs.cost_terms)


@pytest.fixture(scope="module")
def urdf(tmp_path_factory):
    """The URDF both transcriptions read: the real iRonCub Mk1.1 from ``../shared`` where it is
    (CI has it), else the assembled default iRonCub (``jaxmm.assemble_urdf``) in a file."""
    if IRONCUB_URDF.is_file():
        return IRONCUB_URDF
    path = tmp_path_factory.mktemp("reference") / "ironcub.urdf"
    path.write_bytes(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
    return path


@pytest.fixture(scope="module")
def robot(urdf):
    """iRonCub from ``urdf``, with the default robot's joints, frames and stance."""
    default = jaxmm.load_ironcub()
    return jaxmm.load_robot(
        urdf,
        joints=default.model.joint_names,
        check_inertia=False,  # the public Mk1.1 URDF has non-physical elbow inertias
        jet_frames=default.jet_frames,
        contact_frames=default.contact_frames,
        standing_configuration=default.standing_configuration,
    )


@pytest.fixture(scope="module")
def build(robot, urdf):
    """build(name, knots=6, **options) → (task, ReferenceNLP), cached for the module."""
    cache = {}

    def build(name, knots=6, **options):
        key = (name, knots, tuple(sorted(options.items())))
        if key not in cache:
            task = tasks.scenario(name, robot=robot, knots=knots, **options)
            cache[key] = task, ReferenceNLP(task, urdf)
        return cache[key]

    return build


def random_trajectory(task, rng):
    """The initial guess plus large random perturbations: random quaternions (normalised or
    not), ω = 0 at some knots (the small-angle branch of Exp), T_total uniform within bounds."""
    layout, n_knots = task.layout, task.n_knots
    z = np.array(layout.flatten(tasks.initial_guess(task).knots))
    slices = layout.slices()
    for field, sigma in PERTURBATION.items():
        z[:, slices[field]] += sigma * rng.normal(size=z[:, slices[field]].shape)
    quaternions = rng.normal(size=(n_knots, 4))
    if rng.random() < 0.5:
        quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    z[:, slices["base_quaternion"]] = quaternions
    z[rng.random(n_knots) < 0.3, slices["base_angular_velocity"]] = 0.0
    total_time = rng.uniform(task.n_intervals * task.params.min_dt, task.n_intervals * task.params.max_dt)
    return Trajectory(layout.unflatten(jnp.asarray(z)), jnp.asarray(total_time))


def parity(task, nlp, trajectories):
    """Max relative difference per family and cost term (|a − b| / max(1, max |a|)) over the
    trajectories; asserts that both sides give the same families with the same shapes."""
    worst = {}
    for trajectory in trajectories:
        reference = nlp.evaluate(trajectory)
        ours = {name: np.asarray(value) for name, value in _evaluate(task, trajectory).items()}
        assert set(ours) == set(reference), f"family names differ: {sorted(set(ours) ^ set(reference))}"
        reference_costs = nlp.cost_terms(trajectory)
        our_costs = {f"cost {name}": float(value) for name, value in _cost_terms(task, trajectory).items()}
        assert set(our_costs) == {f"cost {name}" for name in reference_costs}
        for name, value in reference.items():
            assert ours[name].shape == value.shape, (name, ours[name].shape, value.shape)
            assert np.all(np.isfinite(value)), name
            error = np.abs(ours[name] - value).max(initial=0.0) / max(1.0, np.abs(value).max(initial=0.0))
            worst[name] = max(worst.get(name, 0.0), error)
        for name, value in reference_costs.items():
            error = abs(our_costs[f"cost {name}"] - value) / max(1.0, abs(value))
            worst[f"cost {name}"] = max(worst.get(f"cost {name}", 0.0), error)
    return worst


def assert_parity(worst):
    bad = {name: error for name, error in worst.items() if not error <= PARITY_TOLERANCE}
    assert not bad, f"JAX and CasADi transcriptions differ (max relative difference): {bad}"


@pytest.mark.parametrize(
    "name, count, options",
    [
        ("take_off", 20, {}),
        ("take_off", 5, dict(integration="backward_euler", slack_penalty="squared")),
        ("jumping", 5, {}),
        ("take_off", 5, dict(joint_torque_limits=True)),
    ],
    ids=["take_off", "take_off-backward_euler-squared_slack", "jumping-no_jets", "take_off-joint_torque"],
)
def test_parity_with_reference(build, name, count, options):
    task, nlp = build(name, **options)
    rng = np.random.default_rng(20220)
    trajectories = [tasks.initial_guess(task)] + [random_trajectory(task, rng) for _ in range(count)]
    worst = parity(task, nlp, trajectories)
    expected = set(nlp.family_names()) | {f"cost {term}" for term in COST_TERMS + ("total",)}
    assert set(worst) == expected
    assert_parity(worst)


def test_reference_is_smooth_at_the_initial_guess(build):
    """The guess has ω = 0 and the standing ρ: the small-angle branches must give finite
    derivatives, and the guess satisfies the integration rows it is built to satisfy."""
    import casadi as cs

    task, nlp = build("take_off")
    guess = tasks.initial_guess(task)
    w = cs.MX.sym("w", nlp.n_variables)
    families, cost = nlp.symbolic(w)
    g = cs.vertcat(*[cs.vec(families[name]) for name in nlp.family_names()])
    jacobian, gradient = cs.Function("derivatives", [w], [cs.jacobian(g, w), cs.gradient(cost["total"], w)])(
        nlp.flatten(guess)
    )
    assert np.all(np.isfinite(jacobian.full())) and np.all(np.isfinite(gradient.full()))
    values = nlp.evaluate(guess)
    for name in ("base_quaternion_integration", "joint_integration", "thrust_integration"):
        np.testing.assert_allclose(values[name], 0.0, atol=1e-15)


@pytest.mark.parametrize("name, options", [("take_off", {}), ("take_off_and_landing", {}),
                                           ("take_off", dict(complementarity_tolerance=1e-6, planar_tolerance=1e-4, slack_limit=0.0)),
                                           ("take_off", dict(joint_torque_limits=True))],
                         ids=["take_off", "take_off_and_landing", "take_off-exact_complementarity",
                              "take_off-joint_torque"])
def test_bounds_match_jax(build, name, options):
    """Inequality bounds and variable boxes (boundary conditions, with and without a
    mid-horizon height; the published complementarity and Scholtes' without slacks, its normal
    and planar rows' σ apart; the joint
    torques' effort limits) agree."""
    task, nlp = build(name, **options)
    ours = constraints.inequality_bounds(task)
    for name, (lower, upper) in nlp.inequality_bounds().items():
        np.testing.assert_array_equal(np.asarray(ours[name][0]), lower, err_msg=name)
        np.testing.assert_array_equal(np.asarray(ours[name][1]), upper, err_msg=name)
    lower, upper = (nlp.flatten(bound) for bound in constraints.variable_bounds(task))
    reference_lower, reference_upper = nlp.variable_bounds()
    labels = [f"{field}[{i}]" for field, sl in nlp.layout.slices().items() for i in range(sl.stop - sl.start)]
    labels = [f"knot {k} {label}" for k in range(task.n_knots) for label in labels] + ["total_time"]
    for ours, reference, side in ((lower, reference_lower, "lower"), (upper, reference_upper, "upper")):
        differ = [(labels[i], float(ours[i]), float(reference[i])) for i in np.flatnonzero(ours != reference)]
        assert not differ, f"{side} variable bounds differ (entry, JAX, reference): {differ}"


@pytest.fixture(scope="module")
def take_off_solution(robot, urdf):
    task = tasks.scenario("take_off", robot=robot, knots=10)
    trajectory, info = solve_ipopt(task, urdf)
    return task, trajectory, info


def test_ipopt_solves_take_off(take_off_solution):
    """IPOPT + MUMPS from the published guess converges; the JAX residuals of the solution
    are within the IPOPT tolerance (1e-4, physical units) and its costs match."""
    task, trajectory, info = take_off_solution
    assert info["success"] and info["status"] == "Solve_Succeeded", info
    tolerance = 1e-4
    values = {name: np.asarray(value) for name, value in _evaluate(task, trajectory).items()}
    bounds = constraints.inequality_bounds(task)
    for name, value in values.items():
        lower, upper = bounds.get(name, (0.0, 0.0))
        violation = np.maximum(np.asarray(lower) - value, value - np.asarray(upper)).max(initial=0.0)
        assert violation <= tolerance, f"{name} violated by {violation}"
    lower, upper = constraints.variable_bounds(task)
    for field in dataclasses.fields(trajectory.knots):
        value = np.asarray(getattr(trajectory.knots, field.name))
        low, up = np.asarray(getattr(lower.knots, field.name)), np.asarray(getattr(upper.knots, field.name))
        assert np.all(value >= low - tolerance) and np.all(value <= up + tolerance), field.name
    assert lower.total_time - tolerance <= trajectory.total_time <= upper.total_time + tolerance
    total = float(_cost_terms(task, trajectory)["total"])
    assert abs(total - info["objective"]) <= 1e-9 * abs(info["objective"])


def test_validate_the_ipopt_solution(take_off_solution):
    """At N = 10 IPOPT meets every constraint, but the jets cannot spin up in ≤ 1 s: the CoM
    reaches 0.80 m by pushing with feet that are off the ground, paid for by complementarity
    slack. ``validate`` must see both facts."""
    from jaxmm import analysis

    task, trajectory, _ = take_off_solution
    report = analysis.validate(task, trajectory)
    constraint_checks = [c for c in report.checks if c.name.startswith("constraint ")]
    assert constraint_checks and all(c.passed for c in constraint_checks), str(report)
    assert "re-simulated CoM" not in report.failed, str(report)
    # Thrust reachable in 1 s (≈ 60 N) is far below the weight, and a CoM at 0.80 m needs the
    # feet off the ground: some airborne corner must push. This is not a take-off.
    assert "no force on corners off the ground" in report.failed, str(report)
    assert report.flight_knots, str(report)
