"""The transcription: block Jacobians against dense autodiff, costs, bounds and scenarios."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxmm
from jaxmm import tasks
from jaxmm.tasks import SCENARIOS, build_task, initial_guess, scenario
from jaxmm.transcription import constraints, costs
from jaxmm.transcription.problem import Weights
from jaxmm.transcription import nlp as transcription
from jaxmm import stagewise
from jaxmm.transcription import variables as jaxmm_variables


def _random_point(task, seed):
    """The initial guess with large random perturbations (scaled variables)."""
    Z, theta = transcription.to_variables(task, initial_guess(task))
    rng = np.random.default_rng(seed)
    Z = Z + 0.3 * rng.normal(size=Z.shape)
    return jnp.asarray(Z), theta * (0.6 + 0.3 * rng.random())


def _dense_jacobian(nlp, blocks_of, K, nz, ng):
    """Assemble block Jacobians of one residual group into a dense (rows, K nz + ng) matrix."""
    z_blocks, znext_blocks, theta_blocks = blocks_of
    count, m = theta_blocks.shape[:2]
    J = np.zeros((count * m, K * nz + ng))
    for k in range(count):
        rows = slice(k * m, (k + 1) * m)
        J[rows, k * nz : (k + 1) * nz] += z_blocks[k]
        if znext_blocks is not None:
            J[rows, (k + 1) * nz : (k + 2) * nz] += znext_blocks[k]
        J[rows, K * nz :] = theta_blocks[k]
    return J


# The backward-Euler, squared-slack variant on jumping (≈ 65 s) under ``pytest -m slow``: keeps the default run under 20 minutes.
@pytest.mark.parametrize("name, options", [
    ("take_off", {}),
    pytest.param("jumping", dict(integration="backward_euler", slack_penalty="squared"), marks=pytest.mark.slow),
])
def test_block_jacobians_equal_dense_autodiff(name, options):
    task = scenario(name, knots=4, **options)
    nlp = transcription.stagewise_nlp(task)
    Z, theta = _random_point(task, seed=1)
    K, nz = Z.shape
    ng = theta.shape[0]
    B = jax.jit(stagewise.blocks)(nlp, Z, theta)  # the path rows through ``path_jacobian``
    assert B.path_linearisation is not None
    groups = {
        "path_equality": (B.path_equality_z, None, B.path_equality_theta),
        "transition_equality": (B.transition_equality_z, B.transition_equality_znext, B.transition_equality_theta),
        "path_inequality": (B.path_inequality_z, None, B.path_inequality_theta),
        "transition_inequality": (B.transition_inequality_z, B.transition_inequality_znext, B.transition_inequality_theta),
    }

    def flat(w):
        residuals = stagewise.residuals(nlp, w[: K * nz].reshape(K, nz), w[K * nz :])
        return {group: getattr(residuals, group).reshape(-1) for group in groups}

    # Every group's dense Jacobian in one compiled program (one compilation instead of four).
    w = jnp.concatenate([Z.reshape(-1), theta])
    dense_of = jax.jit(jax.jacfwd(flat))(w)
    for group, blocks_of in groups.items():
        dense = np.asarray(dense_of[group])
        assembled = _dense_jacobian(nlp, blocks_of, K, nz, ng)
        assert dense.shape == assembled.shape and dense.size > 0
        assert np.abs(dense - assembled).max() <= 1e-12 * max(1.0, np.abs(dense).max()), group

    cost = lambda w: stagewise.residuals(nlp, w[: K * nz].reshape(K, nz), w[K * nz :]).cost  # noqa: E731
    gradient = np.asarray(jax.jit(jax.grad(cost))(w))
    assert np.allclose(gradient[: K * nz], np.asarray(B.cost_z).reshape(-1), rtol=1e-12, atol=1e-9)
    assert np.allclose(gradient[K * nz :], B.cost_theta, rtol=1e-12, atol=1e-9)
    hessian = np.asarray(jax.jit(jax.hessian(cost))(w))
    cost_zz = np.asarray(B.cost_zz.dense())
    for k in range(K):
        block = slice(k * nz, (k + 1) * nz)
        assert np.allclose(hessian[block, block], cost_zz[k], rtol=1e-12, atol=1e-9)
        assert np.allclose(hessian[block, K * nz :], B.cost_ztheta[k], rtol=1e-12, atol=1e-9)
        off = np.delete(hessian[block, : K * nz], np.arange(k * nz, (k + 1) * nz), axis=1)
        assert np.abs(off).max() == 0.0  # the cost is knot-separable
    assert np.allclose(hessian[K * nz :, K * nz :], B.cost_thetatheta, rtol=1e-12, atol=1e-9)


def test_residual_families_match_the_formulation():
    task = scenario("take_off", knots=4)
    trajectory = initial_guess(task)
    values = constraints.evaluate(task, trajectory)
    rows = {name: size for group in transcription.family_rows(task).values() for name, size in group}
    assert set(values) == set(rows)
    for name, value in values.items():
        expected_knots = 5 if name in constraints.PATH_EQUALITIES + constraints.PATH_INEQUALITIES else 4
        assert value.shape == (expected_knots, rows[name]), name
    nlp = transcription.stagewise_nlp(task)
    split = transcription.split_families(task, jax.jit(stagewise.residuals)(nlp, *transcription.to_variables(task, trajectory)))
    for name in values:
        assert np.allclose(split[name], values[name], atol=1e-12), name


def _squares(a):
    """‖a[k]‖² for each knot k of a (N + 1, ...) array."""
    return np.sum(np.square(a).reshape(len(a), -1), axis=1)


def _eq32_terms(task, trajectory):
    """The terms of J (eq. 32; docs/formulation.md, "Cost") written out in NumPy, the SO(3) log
    of l_0 by SciPy: {running, final, initial, slack, horizon}."""
    w = {f.name: float(getattr(task.weights, f.name)) for f in dataclasses.fields(task.weights)}
    x = jax.tree.map(np.asarray, trajectory.knots)
    reference = np.asarray(task.params.reference_configuration)
    posture = x.joint_positions - reference[7:]
    upper = np.isin(np.arange(task.layout.n_joints), task.upper_body_joints)
    running = dict(com_acc=x.com_acceleration, com_vel=x.com_velocity, com_vel_xy=x.com_velocity[:, :2],
                   ang_mom_rate=x.angular_momentum_rate, ang_mom=x.angular_momentum,
                   joint_vel_upper=x.joint_velocities[:, upper], joint_vel_lower=x.joint_velocities[:, ~upper],
                   posture=posture, force=x.contact_forces, force_rate=x.contact_force_rates, thrust=x.thrust,
                   throttle=x.throttle, base_orientation=x.base_quaternion - [0.0, 0.0, 0.0, 1.0])
    l_k = sum(w[name] * _squares(value) for name, value in running.items())
    momentum = sum(_squares(v) for v in (x.com_velocity, x.com_acceleration, x.angular_momentum,
                                         x.angular_momentum_rate))
    rotation = Rotation.from_quat(reference[3:7]).inv() * Rotation.from_quat(x.base_quaternion[0])
    slacks = np.concatenate([x.normal_slack, x.tangential_slack], axis=1)
    T = float(trajectory.total_time)
    return dict(
        running=T / task.n_intervals * np.sum(l_k[:-1]),
        final=(w["final_momentum"] * momentum[-1] + w["final_thrust"] * _squares(x.thrust)[-1]
               + w["final_posture"] * _squares(posture)[-1] + w["final_force"] * _squares(x.contact_forces)[-1]),
        initial=(w["initial_posture"] * _squares(posture)[0] + w["initial_base_orientation"] * rotation.magnitude() ** 2
                 + w["initial_force"] * _squares(x.contact_forces)[0]),
        slack=w["complementarity_slack"] * np.sum(slacks) + w["complementarity_slack_squared"] * np.sum(slacks**2),
        horizon=w["horizon"] * T,
    )


def test_cost_terms_follow_eq_32_and_every_sum_of_them_agrees():
    """Each term of ``cost_terms`` equals eq. (32) written out independently, with every weight a
    distinct non-zero value (a term on the wrong field, knot or weight shows; both slack
    penalties at once); the total, the knot-by-knot ``total_cost`` and the NLP's cost equal their
    sum."""
    rng = np.random.default_rng(5)
    weights = {f.name: rng.uniform(0.5, 2.0) for f in dataclasses.fields(Weights)}
    task = scenario("walk_to_fly", knots=6, weights=weights)
    Z, theta = _random_point(task, seed=2)
    trajectory = transcription.to_trajectory(task, Z, theta)
    terms, expected = costs.cost_terms(task, trajectory), _eq32_terms(task, trajectory)
    for name, value in expected.items():
        assert np.isclose(terms[name], value, rtol=1e-12, atol=0), name
    J = sum(expected.values())
    assert np.isclose(terms["total"], J, rtol=1e-12)
    assert np.isclose(costs.total_cost(task, trajectory), J, rtol=1e-12)
    nlp = transcription.stagewise_nlp(task)
    assert np.isclose(jax.jit(stagewise.residuals)(nlp, Z, theta).cost, J, rtol=1e-12)


def test_a_slack_penalty_moves_the_slack_weight_and_keeps_the_compiled_structure():
    """``with_slack_penalty`` puts the task's one slack weight on Σ ε or on Σ ε², as the builder's
    ``slack_penalty`` does, without changing the task's pytree structure (one compiled solve)."""
    task = scenario("take_off", knots=4)
    w = float(task.weights.complementarity_slack)
    squared = tasks.with_slack_penalty(task, "squared")
    assert (float(squared.weights.complementarity_slack), float(squared.weights.complementarity_slack_squared)) == (
        0.0, w)
    built = scenario("take_off", knots=4, slack_penalty="squared")
    assert jax.tree.all(jax.tree.map(lambda a, b: np.array_equal(a, b), built.weights, squared.weights))
    back = tasks.with_slack_penalty(squared, "linear")
    assert jax.tree.all(jax.tree.map(lambda a, b: np.array_equal(a, b), back.weights, task.weights))
    assert jax.tree.structure(squared) == jax.tree.structure(task)
    with pytest.raises(ValueError, match="slack_penalty must be one of"):
        tasks.with_slack_penalty(task, "cubic")


def test_cost_is_differentiable_in_the_weights():
    task = scenario("take_off", knots=4)
    trajectory = initial_guess(task)
    gradient = jax.grad(lambda w: costs.total_cost(task, trajectory, w))(task.weights)
    # ∂J/∂w_final_thrust = ‖T[N]‖² = 4 · 30².
    assert np.isclose(gradient.final_thrust, 4 * 30.0**2)
    assert gradient.horizon == pytest.approx(float(trajectory.total_time))


def test_boundary_conditions_are_knot_dependent_boxes():
    task = scenario("take_off_and_landing", knots=10)
    lower, upper = constraints.variable_bounds(task)
    assert np.allclose(lower.knots.com[0], [0, 0, 0.57]) and np.allclose(upper.knots.com[0], [0, 0, 0.57])
    assert np.allclose(lower.knots.com[-1], upper.knots.com[-1])
    assert lower.knots.com[5, 2] == pytest.approx(0.80) and lower.knots.com[4, 2] == 0.0
    assert np.all(upper.knots.contact_points[0, :, 2] == 0.0)
    assert np.all(upper.knots.thrust[0] <= 1e-3) and np.allclose(upper.knots.thrust[1], [160, 160, 220, 220])
    assert float(lower.total_time) == pytest.approx(0.5) and float(upper.total_time) == pytest.approx(1.0)
    guess = initial_guess(task)
    nlp = transcription.stagewise_nlp(task)
    Z, _ = transcription.to_variables(task, guess)
    assert Z.shape == nlp.z_lower.shape


def test_all_scenarios_build_at_published_size():
    for name, spec in SCENARIOS.items():
        task = scenario(name)
        assert task.n_intervals == spec["knots"]
        nlp = transcription.stagewise_nlp(task)
        assert nlp.z_lower.shape == (spec["knots"] + 1, task.layout.size)
        assert np.all(np.asarray(nlp.z_lower) <= np.asarray(nlp.z_upper))
    assert scenario("jumping").layout.n_jets == 0
    assert scenario("take_off").layout.size == 178


# Take-off (whose compiled blocks the Jacobian check above left) and walk-to-fly (where it
# failed) in the default run; the other two (≈ 35 s of compiling) under ``pytest -m slow``.
@pytest.mark.parametrize("name", [name if name in ("take_off", "walk_to_fly") else pytest.param(name, marks=pytest.mark.slow)
                                  for name in SCENARIOS])
def test_every_unbounded_variable_enters_the_cost_or_a_constraint(name):
    """A free variable without bounds that no function reads makes every Newton matrix singular
    (ḟ[0] on walk-to-fly, whose cost weighs no ḟ, once cost an inertia correction at every
    iteration). At a random point of each scenario, every such variable has a non-zero
    Jacobian column or cost curvature."""
    task = scenario(name, knots=4)
    nlp = transcription.stagewise_nlp(task)
    Z, theta = _random_point(task, seed=2)
    B = jax.jit(stagewise.blocks)(nlp, Z, theta)
    used = np.abs(np.diagonal(np.asarray(B.cost_zz.dense()), axis1=1, axis2=2))
    for group in ("path_equality", "path_inequality"):
        used = used + np.sum(np.asarray(getattr(B, group + "_z")) ** 2, axis=1)
    for group in ("transition_equality", "transition_inequality"):
        used[:-1] += np.sum(np.asarray(getattr(B, group + "_z")) ** 2, axis=1)
        used[1:] += np.sum(np.asarray(getattr(B, group + "_znext")) ** 2, axis=1)
    lower, upper = np.asarray(nlp.z_lower), np.asarray(nlp.z_upper)
    unbounded = (lower < upper) & ~np.isfinite(lower) & ~np.isfinite(upper)
    names = [field for field, sl in task.layout.slices().items() for _ in range(sl.stop - sl.start)]
    unused = sorted({(int(k), names[j]) for k, j in zip(*np.nonzero(unbounded & (used == 0)))})
    assert not unused, f"{name}: free, unbounded variables that nothing reads (knot, field): {unused}"


@pytest.mark.parametrize("kwargs, message", [
    (dict(knots=-3), "knots must be an integer N ≥ 2"),
    (dict(knots=1), "knots must be an integer N ≥ 2"),
    (dict(final_com=(0.0, 2.0, 0.8)), "outside the workspace bounds"),
    (dict(final_com=(0.0, 0.0)), r"final_com must have shape \(3,\)"),
    (dict(weights=dict(posture=[1.0, 2.0])), "weight 'posture' must be a scalar"),
    (dict(weights=dict(postur=1.0)), "unknown cost weights"),
    (dict(weights=dict(posture=-1.0)), "non-negative"),
    (dict(integration="rk4"), "integration must be one of"),
    (dict(min_dt=-0.1), "time-step bounds"),
    (dict(jet_coefficients=np.zeros((4, 9))), r"jet_coefficients must have shape \(4, 10\)"),
    (dict(complementarity_tolerance=-1e-6), "complementarity_tolerance must be a finite non-negative number"),
    (dict(planar_tolerance=float("nan")), "planar_tolerance must be a finite non-negative number"),
    (dict(slack_limit=-1.0), "slack_limit must be a non-negative number"),
    (dict(planar_relaxation=-0.1), "planar_relaxation must be a finite non-negative number"),
])
def test_bad_task_input(kwargs, message):
    knots = kwargs.pop("knots", 10)
    with pytest.raises(ValueError, match=message):
        scenario("take_off", knots=knots, **kwargs)


def test_exact_complementarity_bounds_the_products_by_sigma_and_fixes_the_slacks():
    """Scholtes' relaxation (``tasks.exact_complementarity``): the normal rows f_z c_z − ε_n ≤ σ_n,
    the planar rows f_z Δc ∓ ε_t within ±σ_t, the slacks boxed to [0, 0]; everything else as
    published, and the leaf types unchanged (the compiled solve is shared). σ_t defaults to
    ``PLANAR_TOLERANCE``, and None gives the planar rows σ_n."""
    task = scenario("take_off", knots=6)
    exact = tasks.exact_complementarity(task, 2e-6, 3e-5)
    nc = len(task.robot.contact_frames)
    published, bounds = constraints.inequality_bounds(task), constraints.inequality_bounds(exact)
    np.testing.assert_array_equal(bounds["normal_complementarity"][1], np.full(nc, 2e-6))
    np.testing.assert_array_equal(published["normal_complementarity"][1], np.zeros(nc))
    np.testing.assert_array_equal(bounds["planar_complementarity"][0], np.r_[np.full(2 * nc, -np.inf), np.full(2 * nc, -3e-5)])
    np.testing.assert_array_equal(bounds["planar_complementarity"][1], np.r_[np.full(2 * nc, 3e-5), np.full(2 * nc, np.inf)])
    for name in ("friction_cone", "corner_com", "jet_com"):
        for ours, theirs in zip(bounds[name], published[name]):
            np.testing.assert_array_equal(ours, theirs)
    (lower, upper), (_, published_upper) = constraints.variable_bounds(exact), constraints.variable_bounds(task)
    for name in ("normal_slack", "tangential_slack"):
        np.testing.assert_array_equal(getattr(lower.knots, name), 0.0)
        np.testing.assert_array_equal(getattr(upper.knots, name), 0.0)
        assert np.all(np.isinf(getattr(published_upper.knots, name)))
    assert jax.tree.map(jax.typeof, exact) == jax.tree.map(jax.typeof, task)
    assert float(tasks.exact_complementarity(task).params.planar_tolerance) == tasks.PLANAR_TOLERANCE
    assert float(tasks.exact_complementarity(task, 2e-6, None).params.planar_tolerance) == 2e-6
    for args, label in (((-1.0,), "tolerance"), ((1e-6, np.inf), "planar_tolerance")):
        with pytest.raises(ValueError, match=f"^{label} must be a finite non-negative number"):
            tasks.exact_complementarity(task, *args)


@pytest.mark.parametrize("share", [1.0, 0.1])
def test_the_complementarity_rows_alone_are_marked_for_the_relaxation_homotopy(share):
    """``Options.relaxation`` widens the bounds that the NLP marks: the normal rows' upper bound
    (+1), the planar rows' upper bounds (+κ_t) and their lower bounds (−κ_t), κ_t the task's
    ``planar_relaxation`` (default 1), nothing else (the joint torques' rows included)."""
    task = scenario("take_off", knots=2, joint_torque_limits=True, planar_relaxation=share)
    nlp = transcription.stagewise_nlp(task)
    nc = len(task.robot.contact_frames)
    for group, marks in (("path_inequality", nlp.path_relaxation), ("transition_inequality", nlp.transition_relaxation)):
        offset = 0
        for name, size in transcription.family_rows(task)[group]:
            expected = dict(normal_complementarity=np.ones(nc),
                            planar_complementarity=share * np.r_[np.ones(2 * nc), -np.ones(2 * nc)]).get(
                name, np.zeros(size))
            np.testing.assert_array_equal(np.asarray(marks[offset:offset + size]), expected, err_msg=name)
            offset += size
        assert offset == marks.shape[0]


def test_unknown_scenario_and_missing_jet_model():
    with pytest.raises(ValueError, match="unknown scenario 'hover'; scenarios: take_off"):
        scenario("hover")
    robot = jaxmm.load_ironcub()
    with pytest.raises(ValueError, match="has 4 jets: jet_coefficients"):
        build_task(robot, (0, 0, 0.57), (0, 0, 0.8), 10, {})
    with pytest.raises(jaxmm.UnknownNameError, match="unknown frame"):
        jaxmm.load_robot(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()), jet_frames=["nozzle"])


# The backward-Euler variant differs only in two transition families; it runs under
# ``pytest -m slow`` (≈ 2 minutes), to keep the default run within its 20-minute budget.
@pytest.mark.parametrize("integration", [pytest.param("backward_euler", marks=pytest.mark.slow), "trapezoidal"])
def test_constraint_curvature_matches_jax_hessian(integration):
    """The transcription's own Hessians (path: kinematics linearised + their own curvature, over
    the columns the rows are nonlinear in; transition: over its nonlinear columns + T_total's)
    equal ``jax.hessian`` of y·c at a perturbed guess with random multipliers."""
    # 4 knots, as in the Jacobian check above: the compiled ``blocks`` is the one it compiled.
    task = scenario("take_off", knots=4, integration=integration)
    nlp = transcription.stagewise_nlp(task)
    Z, theta = transcription.to_variables(task, initial_guess(task))
    key = jax.random.PRNGKey(0)
    Z = Z + 0.1 * jax.random.normal(key, Z.shape)
    r = jax.eval_shape(stagewise.residuals, nlp, Z, theta)  # the rows' shapes only
    groups = ("path_equality", "transition_equality", "path_inequality", "transition_inequality")
    y = [jax.random.normal(k, getattr(r, g).shape) for k, g in zip(jax.random.split(key, 4), groups)]
    # With the kinematics and their Jacobian from the Jacobian pass (as the solver calls it).
    plain = jax.jit(stagewise.blocks)(nlp, Z, theta)
    variants = [jax.jit(stagewise.constraint_curvature)(nlp, Z, theta, *y, path_linearisation=plain.path_linearisation)]
    if integration == "backward_euler":
        # Without a linearisation handed over, the kinematics computed inside (no solver calls
        # it so; the path rows do not depend on the integration): in the slow run, one
        # compilation fewer in the default one.
        variants.append(jax.jit(stagewise.constraint_curvature)(nlp, Z, theta, *y))
    if integration == "trapezoidal":  # the path rows do not depend on it: once is enough
        # With the path multipliers the Jacobian pass also carries the kinematics' curvature at
        # them (as the solver calls it): the same Jacobian blocks, and the same Hessian.
        given = jax.jit(stagewise.blocks)(nlp, Z, theta, path_multipliers=(y[0], y[2]))
        assert len(given.path_linearisation) == 3
        for name in ("path_equality_z", "path_equality_theta", "path_inequality_z", "path_inequality_theta"):
            a, b = np.asarray(getattr(given, name)), np.asarray(getattr(plain, name))
            assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(b).max()), name
        variants.append(jax.jit(stagewise.constraint_curvature)(nlp, Z, theta, *y,
                                                                path_linearisation=given.path_linearisation))
        # The coupling blocks kept on the transition curvature's columns (as the solver keeps
        # them): the same blocks, and the same products with vectors.
        compact = jax.jit(functools.partial(stagewise.constraint_curvature, compact=True))(
            nlp, Z, theta, *y, path_linearisation=given.path_linearisation)
        coupling, L = compact[1], np.asarray(variants[-1][1])
        assert isinstance(coupling, stagewise.Coupling) and len(coupling.rows) * len(coupling.columns) < L[0].size
        np.testing.assert_array_equal(np.asarray(coupling.dense()), L)
        for a, b in zip(compact[::2] + compact[3:], variants[-1][::2] + variants[-1][3:]):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        x = np.asarray(jax.random.normal(key, Z.shape))
        np.testing.assert_allclose(np.asarray(coupling.below(x)), np.einsum("kab,kb->ka", L, x[:-1]), atol=1e-12)
        np.testing.assert_allclose(np.asarray(coupling.above(x)), np.einsum("kba,kb->ka", L, x[1:]), atol=1e-12)
        zero = stagewise.zero_coupling(nlp, Z.shape[0], Z.shape[1], Z.dtype)
        assert jax.tree.structure(zero) == jax.tree.structure(coupling) and not np.any(np.asarray(zero.dense()))

    # Both against the dense Hessian of Σ y·c over all of (Z, θ), cut into blocks.
    K, nz = Z.shape

    def weighted(w):
        residuals = stagewise.residuals(nlp, w[: K * nz].reshape(K, nz), w[K * nz :])
        return sum(jnp.sum(getattr(residuals, g) * yi) for g, yi in zip(groups, y))

    dense = np.asarray(jax.jit(jax.hessian(weighted))(jnp.concatenate([Z.reshape(-1), theta])))
    for blocks in variants:
        _assert_curvature_blocks_match(blocks, dense, K, nz)


def _assert_curvature_blocks_match(blocks, dense, K, nz):
    """``constraint_curvature``'s (D, L, B, C) equal the dense Hessian over (Z, θ) cut into blocks,
    to 1e-10 of its largest entry."""
    D, L, B, C = (np.asarray(x) for x in blocks)
    scale = max(1.0, np.abs(dense).max())
    for k in range(K):
        now = slice(k * nz, (k + 1) * nz)
        assert np.abs(D[k] - dense[now, now]).max() <= 1e-10 * scale
        assert np.abs(B[k] - dense[now, K * nz :]).max() <= 1e-10 * scale
        if k:
            assert np.abs(L[k - 1] - dense[now, (k - 1) * nz : k * nz]).max() <= 1e-10 * scale
    assert np.abs(C - dense[K * nz :, K * nz :]).max() <= 1e-10 * scale


@pytest.mark.parametrize("columns", [(0, 0), (-1,), (10_000,)])
def test_bad_transition_curvature_columns_are_refused(columns):
    task = scenario("take_off", knots=2)
    nlp = transcription.stagewise_nlp(task)
    bad = dataclasses.replace(nlp, functions=dataclasses.replace(
        nlp.functions, transition_curvature_columns=lambda args: columns))
    Z, theta = transcription.to_variables(task, initial_guess(task))
    r = jax.eval_shape(stagewise.residuals, nlp, Z, theta)
    y = [jnp.ones(getattr(r, g).shape) for g in ("path_equality", "transition_equality", "path_inequality",
                                               "transition_inequality")]
    with pytest.raises(ValueError, match="transition_curvature_columns must be distinct columns"):
        stagewise.constraint_curvature(bad, Z, theta, *y)


def test_bad_transition_through_columns_are_refused():
    """Tangent columns must be distinct curvature columns."""
    task = scenario("take_off", knots=2)
    nlp = transcription.stagewise_nlp(task)
    Z, theta = transcription.to_variables(task, initial_guess(task))
    r = jax.eval_shape(stagewise.residuals, nlp, Z, theta)
    y = [jnp.ones(getattr(r, g).shape) for g in ("path_equality", "transition_equality", "path_inequality",
                                               "transition_inequality")]
    outside = int(np.setdiff1d(np.arange(2 * nlp.knot_size), nlp.functions.transition_curvature_columns(task))[0])
    for through in ((outside,), (nlp.functions.transition_curvature_columns(task)[0],) * 2):
        bad = dataclasses.replace(nlp, functions=dataclasses.replace(
            nlp.functions, transition_through_columns=lambda args, through=through: through))
        with pytest.raises(ValueError, match="transition_through_columns must be distinct"):
            stagewise.constraint_curvature(bad, Z, theta, *y)


# The backward-Euler variant (≈ 35 s) under ``pytest -m slow``: keeps the default run under 20 minutes.
@pytest.mark.parametrize("integration", [pytest.param("backward_euler", marks=pytest.mark.slow), "trapezoidal"])
def test_row_supports_cover_every_nonzero_of_the_jacobians(integration):
    """The declared sparsity (``constraints.FAMILY_FIELDS``) the solver's Gram products rely on:
    at random points, every Jacobian entry outside a run's columns is exactly zero, and the
    supports are not trivially everything (each run misses some columns)."""
    task = scenario("walk_to_fly", knots=3, integration=integration)
    nlp = transcription.stagewise_nlp(task)
    supports = stagewise.row_supports(nlp)
    nz = nlp.knot_size
    blocks = jax.jit(stagewise.blocks)
    for seed in range(3):
        Z, theta = _random_point(task, seed)
        B = blocks(nlp, Z, theta)
        for group, runs in supports.items():
            jz = np.asarray(getattr(B, group + "_z"))
            jn = None if group.startswith("path") else np.asarray(getattr(B, group + "_znext"))
            assert runs[-1].stop == jz.shape[1]
            for run in runs:
                for block, columns in ((jz, run.now), (jn, run.next)):
                    if block is None:
                        continue
                    outside = np.setdiff1d(np.arange(nz), columns)
                    assert len(outside) > 0
                    assert np.all(block[:, run.start:run.stop][:, :, outside] == 0.0), (group, run.start)
                    assert np.any(block[:, run.start:run.stop] != 0.0), (group, run.start)


@pytest.mark.parametrize("name", ["take_off", "jumping"])
def test_the_knot_layout_puts_the_coupled_columns_last(name):
    """The block factorisation eliminates each knot's variables with the columns that the
    transition rows couple to the next knot last (``linalg.coupled_order``): in the layout of
    ``variables.FIELDS`` that order is the identity, so no block is reordered."""
    from jaxmm.solver import linalg, rows
    nlp = transcription.stagewise_nlp(scenario(name, knots=3))
    coupled = rows.coupled_columns(stagewise.row_supports(nlp))
    order, s = linalg.coupled_order(nlp.knot_size, coupled)
    assert 0 < s < nlp.knot_size
    assert order == tuple(range(nlp.knot_size))


def test_resample_interpolates_knots_in_time_and_keeps_unit_quaternions():
    task = scenario("take_off", knots=6, keep_horizon=True)
    guess = initial_guess(task)
    rng = np.random.default_rng(3)
    # every field affine in time, so linear interpolation must reproduce it exactly
    slope, offset = (jax.tree.map(lambda v: rng.normal(size=v.shape[1:]), guess.knots) for _ in range(2))
    time = np.linspace(0.0, 1.0, 7)
    knots = jax.tree.map(lambda a, b: a + np.multiply.outer(time, b), offset, slope)
    # a rotation about z by up to 1.2 rad, with the sign of every other knot flipped (same rotations)
    angles = np.linspace(0.0, 1.2, 7)
    quaternions = np.stack([np.zeros(7), np.zeros(7), np.sin(angles / 2), np.cos(angles / 2)], axis=1)
    flipped = quaternions * np.where(np.arange(7) % 2, -1.0, 1.0)[:, None]
    trajectory = jaxmm_variables.Trajectory(dataclasses.replace(knots, base_quaternion=jnp.asarray(flipped)),
                                           jnp.asarray(2.5))
    fine = jaxmm_variables.resample(trajectory, 25)
    fine_time = np.linspace(0.0, 1.0, 25)
    expected = jax.tree.map(lambda a, b: a + np.multiply.outer(fine_time, b), offset, slope)
    for name in jaxmm_variables.FIELDS:
        if name != "base_quaternion":
            np.testing.assert_allclose(getattr(fine.knots, name), getattr(expected, name), atol=1e-12, err_msg=name)
    q = np.asarray(fine.knots.base_quaternion)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    assert np.all(q[:, 3] > 0.8)  # the flipped knots were brought back to one side before interpolating
    # normalised linear interpolation of a rotation about z stays about z, angles in order
    np.testing.assert_allclose(q[:, :2], 0.0, atol=1e-15)
    assert np.all(np.diff(np.arctan2(q[:, 2], q[:, 3])) > 0)
    np.testing.assert_allclose(2 * np.arctan2(q[[0, -1], 2], q[[0, -1], 3]), [0.0, 1.2], atol=1e-14)
    assert float(fine.total_time) == 2.5
    same = jaxmm_variables.resample(trajectory, 7)
    np.testing.assert_allclose(same.knots.com, trajectory.knots.com, atol=1e-15)
    np.testing.assert_allclose(np.abs(np.sum(same.knots.base_quaternion * flipped, axis=1)), 1.0, atol=1e-14)
    assert jaxmm_variables.resample(fine, 4).n_knots == 4


@pytest.mark.parametrize("call, error, message", [
    (lambda t: jaxmm_variables.resample(t, 1), ValueError, "n_knots must be an integer ≥ 2, got 1"),
    (lambda t: jaxmm_variables.resample(t, 10.5), ValueError, "n_knots must be an integer ≥ 2, got 10.5"),
    (lambda t: jaxmm_variables.resample(t, True), ValueError, "n_knots must be an integer ≥ 2, got True"),
    (lambda t: jaxmm_variables.resample(t.knots, 10), TypeError, "trajectory must be a Trajectory, got Knot"),
], ids=["one knot", "fractional", "bool", "not a trajectory"])
def test_resample_bad_input(call, error, message):
    with pytest.raises(error, match=message):
        call(initial_guess(scenario("take_off", knots=4, keep_horizon=True)))


def test_joint_torque_family_rows_supports_and_curvature():
    """With ``joint_torque_limits``, the transition inequalities end with the joint torques at
    knot k+1 (the same as ``analysis.joint_torques``' at knots 1..N), bounded by the URDF's effort
    limits; their Jacobian (along their own columns alone) equals ``jax.jacfwd``'s and stays inside
    the declared supports, and the transcription's own
    Hessian of y·h (tangents along ``transition_through_columns`` alone, the rest by symmetry)
    equals ``jax.hessian`` of the whole NLP."""
    from jaxmm import analysis

    task = scenario("take_off", knots=2, joint_torque_limits=True)
    nlp = transcription.stagewise_nlp(task)
    n = task.robot.model.n_joints
    through = nlp.functions.transition_through_columns(task)
    assert set(through) < set(nlp.functions.transition_curvature_columns(task))
    assert [name for name, _ in transcription.family_rows(task)["transition_inequality"]] == [
        "planar_complementarity", "joint_torque"]
    effort = np.asarray(task.robot.model.effort_limits)
    np.testing.assert_array_equal(np.asarray(nlp.transition_upper[-n:]), effort)
    np.testing.assert_array_equal(np.asarray(nlp.transition_lower[-n:]), -effort)
    Z, theta = _random_point(task, seed=4)
    trajectory = transcription.to_trajectory(task, Z, theta)
    rows = np.asarray(jax.jit(stagewise.residuals)(nlp, Z, theta).transition_inequality)[:, -n:]
    torques = analysis.joint_torques(task, trajectory).torques[1:]
    assert np.abs(rows - torques).max() <= 1e-10 * np.abs(torques).max()

    B = jax.jit(stagewise.blocks)(nlp, Z, theta)
    # The Jacobian along the torque rows' own columns (``transition_inequality_jacobian``)
    # equals ``jax.jacfwd`` of the whole function.
    dense = jax.jit(jax.vmap(jax.jacfwd(nlp.functions.transition_inequality, argnums=(1, 2, 3)),
                             in_axes=(None, 0, 0, None)))(task, Z[:-1], Z[1:], theta)
    for ours, reference in zip((B.transition_inequality_z, B.transition_inequality_znext, B.transition_inequality_theta),
                               dense):
        assert np.abs(np.asarray(ours) - np.asarray(reference)).max() <= 1e-12 * np.abs(np.asarray(reference)).max()
    run = stagewise.row_supports(nlp)["transition_inequality"][-1]
    for block, columns in ((B.transition_inequality_z, run.now), (B.transition_inequality_znext, run.next)):
        outside = np.setdiff1d(np.arange(nlp.knot_size), columns)
        assert np.all(np.asarray(block)[:, run.start:run.stop][:, :, outside] == 0.0)

    K, nz = Z.shape
    r = jax.eval_shape(stagewise.residuals, nlp, Z, theta)
    keys = jax.random.split(jax.random.PRNGKey(1))
    y = [jnp.zeros(r.path_equality.shape), jax.random.normal(keys[0], r.transition_equality.shape),
         jnp.zeros(r.path_inequality.shape), jax.random.normal(keys[1], r.transition_inequality.shape)]
    curvature = jax.jit(stagewise.constraint_curvature)(nlp, Z, theta, *y)

    def weighted(w):
        residuals = stagewise.residuals(nlp, w[: K * nz].reshape(K, nz), w[K * nz :])
        return jnp.sum(residuals.transition_equality * y[1]) + jnp.sum(residuals.transition_inequality * y[3])

    dense = np.asarray(jax.jit(jax.hessian(weighted))(jnp.concatenate([Z.reshape(-1), theta])))
    _assert_curvature_blocks_match(curvature, dense, K, nz)


def test_knot_hessian_blocks_added_where_they_are_nonzero():
    """A ``KnotHessian`` (diagonal plus a block on a few columns) equals its dense blocks, and
    added into other blocks gives their sum; a dense Hessian wrapped by ``of`` likewise."""
    rng = np.random.default_rng(5)
    K, n, columns = 3, 7, (1, 4, 5)
    diagonal, block = rng.normal(size=(K, n)), rng.normal(size=(K, 3, 3))
    compact = stagewise.KnotHessian(jnp.asarray(diagonal), jnp.asarray(block), columns)
    expected = np.zeros((K, n, n))
    for k in range(K):
        expected[k] = np.diag(diagonal[k])
        expected[k][np.ix_(columns, columns)] += block[k]
    D = rng.normal(size=(K, n, n))
    assert np.array_equal(compact.dense(), expected)
    assert np.allclose(compact.added_to(jnp.asarray(D), 2.5), D + 2.5 * expected, rtol=0, atol=1e-14)
    dense = stagewise.KnotHessian.of(jnp.asarray(expected))
    assert dense.columns == tuple(range(n))
    assert np.array_equal(dense.dense(), expected)
    assert np.allclose(dense.added_to(jnp.asarray(D), -1.0), D - expected, rtol=0, atol=1e-14)
