"""The interior-point solver on small stage-wise problems with known solutions."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import filter as filters
from jaxmm.solver import interior_point as ip
from jaxmm.solver import scaling
from jaxmm import stagewise
from jaxmm.stagewise import StagewiseFunctions, StagewiseNLP

K = 12
EMPTY = jnp.zeros(0)


# A double integrator (position, velocity, control) over K knots with a free global drift θ:
# x⁺ = x + 0.1 v + 0.01 θ, v⁺ = v + 0.1 u; cost ½(x² + 0.1 v² + u²) per knot + ½(θ − a)².
def _knot_cost(a, z, theta, d):
    return 0.5 * (z[0] ** 2 + 0.1 * z[1] ** 2 + z[2] ** 2) + 0.0 * d


def _global_cost(a, theta):
    return 0.5 * (theta[0] - a) ** 2


def _dynamics(a, z, z_next, theta):
    return jnp.array([z_next[0] - z[0] - 0.1 * z[1] - 0.01 * theta[0], z_next[1] - z[1] - 0.1 * z[2]])


def _no_path(a, z, theta):
    return EMPTY


def _no_transition(a, z, z_next, theta):
    return EMPTY


def _control_energy(a, z, theta):
    return z[2:3] ** 2  # an inequality u² ≤ bound (nonlinear)


INTEGRATOR = StagewiseFunctions(_knot_cost, _global_cost, _no_path, _dynamics, _no_path, _no_transition)
CAPPED = StagewiseFunctions(_knot_cost, _global_cost, _no_path, _dynamics, _control_energy, _no_transition)


def integrator(functions=INTEGRATOR, a=2.0, start=1.0, u_max=np.inf, energy_cap=None):
    lower = jnp.full((K, 3), -jnp.inf).at[0, :2].set([start, 0.0]).at[:, 2].set(-u_max)
    upper = jnp.full((K, 3), jnp.inf).at[0, :2].set([start, 0.0]).at[:, 2].set(u_max)
    path_bounds = (EMPTY, EMPTY) if energy_cap is None else (jnp.array([-jnp.inf]), jnp.array([energy_cap]))
    return StagewiseNLP(
        args=jnp.asarray(a), knot_data=jnp.zeros(K), z_lower=lower, z_upper=upper,
        theta_lower=jnp.full(1, -jnp.inf), theta_upper=jnp.full(1, jnp.inf),
        path_lower=path_bounds[0], path_upper=path_bounds[1], transition_lower=EMPTY, transition_upper=EMPTY,
        functions=functions,
    )


def _dense_kkt_solution(a=2.0, start=1.0):
    """The equality-constrained QP solved through its dense KKT system."""
    n = K * 3 + 1

    def f(w):
        Z = w[:-1].reshape(K, 3)
        return jnp.sum(jax.vmap(_knot_cost, (None, 0, None, None))(a, Z, w[-1:], 0.0)) + _global_cost(a, w[-1:])

    def c(w):
        Z = w[:-1].reshape(K, 3)
        dynamics = jax.vmap(_dynamics, (None, 0, 0, None))(a, Z[:-1], Z[1:], w[-1:]).reshape(-1)
        return jnp.concatenate([dynamics, Z[0, :2] - jnp.array([start, 0.0])])

    w0 = jnp.zeros(n)
    H, g, A, b = jax.hessian(f)(w0), jax.grad(f)(w0), jax.jacfwd(c)(w0), -c(w0)
    kkt = np.block([[H, A.T], [A, np.zeros((A.shape[0], A.shape[0]))]])
    return np.linalg.solve(kkt, np.concatenate([-g, b]))[:n]


OPTIONS = ip.Options(tolerance=1e-9, stationarity=1e-9)
solve = jax.jit(ip.solve, static_argnames="options")


def test_equality_constrained_qp_matches_dense_kkt():
    solution = solve(integrator(), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    found = np.concatenate([np.asarray(solution.Z).reshape(-1), solution.theta])
    assert np.abs(found - _dense_kkt_solution()).max() <= 1e-11  # one Newton step solves a QP (seen: 3.9e-13)
    assert float(solution.violation) <= 1e-9
    assert np.isfinite(np.asarray(solution.history)[: int(solution.iterations)]).all()


def test_bounds_are_kept_and_active_at_the_solution():
    unbounded = _dense_kkt_solution().reshape(-1)[:-1].reshape(K, 3)
    u_max = 0.5 * np.abs(unbounded[:, 2]).max()
    solution = solve(integrator(u_max=u_max), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    u = np.asarray(solution.Z[:, 2])
    assert np.all(np.abs(u) <= u_max + 1e-15)  # iterates stay in the box exactly
    assert np.isclose(np.abs(u).max(), u_max)


@pytest.mark.parametrize("stationarity", [1e-4, 1e-9])
def test_the_barrier_parameter_stops_at_ipopts_floor(stationarity):
    """μ decreases no further than stationarity / (barrier_tolerance_factor + 1) (IPOPT's floor:
    a barrier problem solved there meets the stationarity tolerance), and the solve converges."""
    unbounded = _dense_kkt_solution().reshape(-1)[:-1].reshape(K, 3)
    options = dataclasses.replace(OPTIONS, stationarity=stationarity)
    solution = solve(integrator(u_max=0.5 * np.abs(unbounded[:, 2]).max()), jnp.zeros((K, 3)), jnp.zeros(1),
                     options=options)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    barrier = np.asarray(solution.history)[: int(solution.iterations), ip.HISTORY_COLUMNS.index("barrier")]
    floor = stationarity / (options.barrier_tolerance_factor + 1)
    assert barrier.min() >= floor * (1 - 1e-12)
    if stationarity == 1e-9:
        assert barrier.min() < 1e-4 / (options.barrier_tolerance_factor + 1)


def test_nonlinear_inequality_matches_the_equivalent_box():
    """u² ≤ c as a path inequality gives the same optimum as the box |u| ≤ √c."""
    cap = 0.01
    boxed = solve(integrator(u_max=np.sqrt(cap)), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    inequality = solve(integrator(CAPPED, energy_cap=cap), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    assert ip.Status(int(inequality.status)) is ip.Status.CONVERGED
    assert np.abs(np.asarray(inequality.Z) - np.asarray(boxed.Z)).max() <= 1e-6
    assert np.all(np.asarray(inequality.multipliers.path_inequality) >= -1e-12)


def test_vmap_over_parameters_equals_a_loop():
    targets = jnp.array([0.0, 1.0, 3.0])
    starts = jnp.array([1.0, -0.5, 0.2])
    batched = jax.jit(jax.vmap(lambda a, s: ip.solve(integrator(a=a, start=s), jnp.zeros((K, 3)), jnp.zeros(1), OPTIONS)))(
        targets, starts
    )
    for i in range(3):
        single = solve(integrator(a=targets[i], start=starts[i]), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
        assert np.allclose(batched.Z[i], single.Z, atol=1e-10)
        assert int(batched.status[i]) == int(single.status) == ip.Status.CONVERGED
        expected = _dense_kkt_solution(a=float(targets[i]), start=float(starts[i]))
        assert np.abs(np.concatenate([np.asarray(single.Z).reshape(-1), single.theta]) - expected).max() <= 1e-11


def _out_of_reach(u_max):
    """The integrator with |u| ≤ u_max, no drift (θ = 0) and the last position pinned at 50: for
    small u_max, infeasible."""
    nlp = integrator(u_max=u_max)
    return StagewiseNLP(**{**nlp.__dict__, "z_lower": nlp.z_lower.at[-1, 0].set(50.0), "z_upper": nlp.z_upper.at[-1, 0].set(50.0),
                           "theta_lower": jnp.zeros(1), "theta_upper": jnp.zeros(1)})


def test_infeasible_problem_is_reported_with_finite_numbers():
    """x⁺ = x + 0.1 v + …, u fixed at 0 and the last position pinned far away: infeasible."""
    nlp = _out_of_reach(0.0)
    solution = solve(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options=ip.Options(max_iterations=300))
    assert ip.Status(int(solution.status)) is ip.Status.INFEASIBLE
    assert np.all(np.isfinite(np.asarray(solution.Z))) and np.isfinite(float(solution.violation))
    assert float(solution.violation) > 1.0


def test_short_steps_that_no_longer_cut_the_violation_start_the_restoration_phase():
    """|u| ≤ 0.01 and θ = 0 cannot carry x to 50 in K knots. The Newton steps run into the control
    bounds and are cut to ≈ 1e-5 (or rejected), so the violation hardly moves. After
    max_short_steps such iterations the restoration phase starts without a step. Without the
    rule it starts only after max_rejections rejections in a row (iteration 41 here). Both
    solves end at the same least-infeasible point."""
    nlp = _out_of_reach(0.01)
    options = ip.Options(max_iterations=300)
    column = ip.HISTORY_COLUMNS.index
    solutions = {}
    for rule in (options.max_short_steps, 0):
        solution = solve(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options=dataclasses.replace(options, max_short_steps=rule))
        assert ip.Status(int(solution.status)) is ip.Status.INFEASIBLE
        history = np.asarray(solution.history)[: int(solution.iterations)]
        solutions[rule] = solution, int(np.argmax(history[:, column("restoration")] == 1)), history
    on, first, history = solutions[options.max_short_steps]
    off, first_off, _ = solutions[0]
    assert first == options.max_short_steps + 1 < first_off
    assert np.all(history[:first, column("step_length")] < options.short_step)
    assert history[first - 1, column("step_length")] == 0.0  # the iteration that gave up takes no step
    assert int(on.iterations) < int(off.iterations)
    assert float(on.violation) == pytest.approx(float(off.violation), rel=1e-9) and float(on.violation) > 1.0


def test_a_restoration_point_within_tolerance_that_the_filter_blocks_ends_the_phase():
    """Wächter & Biegler's example after its first iteration, put in the restoration phase by hand
    with a filter entry that turns down every point (violation −1, merit −1e300): the phase's
    steps reach the constraints to within the tolerance, the phase ends there with the filter
    emptied, and the solve converges. Without filter resets left (max_filter_resets = 0) the
    phase cannot end, and fails at that feasible point: ``STALLED``, not ``INFEASIBLE``."""
    nlp, Z0 = _wachter_biegler()
    after_first = ip.advance(nlp, ip.start(nlp, Z0, jnp.zeros(1), OPTIONS), OPTIONS, until=1)
    assert float(after_first.violation) > 0.1
    blocking = filters.augment(after_first.filter, jnp.asarray(-1.0), jnp.asarray(-1e300), jnp.asarray(True))
    entered = dataclasses.replace(after_first, restoring=jnp.asarray(True), filter=blocking,
                                  restoration_theta=jnp.asarray(1e10))
    restored = ip.advance(nlp, entered, OPTIONS)
    assert ip.Status(int(restored.status)) is ip.Status.CONVERGED
    history = np.asarray(restored.history)[: int(restored.iterations)]
    assert history[1, ip.HISTORY_COLUMNS.index("restoration")] == 1 and not bool(restored.restoring)
    no_resets = dataclasses.replace(OPTIONS, max_filter_resets=0, max_restoration_iterations=20)
    stuck = ip.advance(nlp, entered, no_resets)
    assert ip.Status(int(stuck.status)) is ip.Status.STALLED and float(stuck.violation) <= OPTIONS.tolerance
    assert np.all(np.asarray(stuck.history)[2: int(stuck.iterations), ip.HISTORY_COLUMNS.index("restoration")] == 1)


def test_bad_short_step_options_are_refused_by_name():
    with pytest.raises(ValueError, match="short_step"):
        ip.Options(short_step=0.0)
    with pytest.raises(ValueError, match="max_short_steps"):
        ip.Options(max_short_steps=-1)


def _wachter_biegler():
    """Wächter & Biegler's example (Math. Program. 88, 2000), one copy per knot: min x₁ s.t.
    x₁² − x₂ − 1 = 0, x₁ − x₃ − ½ = 0, x₂, x₃ ≥ 0; the solution is (1, 0, ½). From (−2, 1, 1)
    line-search interior-point methods without a restoration phase stop at infeasible points."""

    def circle(a, z, theta):
        return jnp.array([z[0] ** 2 - z[1] - 1.0, z[0] - z[2] - 0.5])

    functions = StagewiseFunctions(lambda a, z, theta, d: z[0] + 0.0 * d, lambda a, theta: 0.0 * theta[0], circle,
                                   _no_transition, _no_path, _no_transition)
    nlp = StagewiseNLP(
        args=jnp.zeros(()), knot_data=jnp.zeros(3), z_lower=jnp.tile(jnp.array([-jnp.inf, 0.0, 0.0]), (3, 1)),
        z_upper=jnp.full((3, 3), jnp.inf), theta_lower=jnp.zeros(1), theta_upper=jnp.zeros(1),
        path_lower=EMPTY, path_upper=EMPTY, transition_lower=EMPTY, transition_upper=EMPTY, functions=functions,
    )
    return nlp, jnp.tile(jnp.array([-2.0, 1.0, 1.0]), (3, 1))


def test_the_restoration_phase_leaves_the_infeasible_point_of_wachter_and_biegler():
    """With the restoration phase entered at the first rejected step, the solve converges to
    (1, 0, ½) through restoration iterations (marked in the history); without it, the solve
    stops ``INFEASIBLE``, with IPOPT's inertia correction at the spurious point the example was
    built for: x₂ = x₃ = 0, where the linearised constraints and the bounds are incompatible."""
    nlp, Z0 = _wachter_biegler()
    options = dataclasses.replace(OPTIONS, max_rejections=1)
    restored = solve(nlp, Z0, jnp.zeros(1), options=options)
    assert ip.Status(int(restored.status)) is ip.Status.CONVERGED
    np.testing.assert_allclose(restored.Z, np.tile([1.0, 0.0, 0.5], (3, 1)), atol=1e-6)
    history = np.asarray(restored.history)[: int(restored.iterations)]
    restoring = history[:, ip.HISTORY_COLUMNS.index("restoration")] == 1
    assert restoring.any() and np.all(history[restoring, ip.HISTORY_COLUMNS.index("step_length")] > 0)
    assert not restoring[-1]

    # IPOPT's inertia correction (from a third of the last δ_w) keeps δ_w ≈ 1e10 near the spurious
    # point, so that the steps converge to it; the default's faster decrease lets the iterates
    # leave it another way (x₁ = −13.8, violation 188), still INFEASIBLE.
    unrestored = dataclasses.replace(options, max_restoration_iterations=0)
    for decrease in (1 / 3, ip.Options.regularisation_decrease):
        stuck = solve(nlp, Z0, jnp.zeros(1), options=dataclasses.replace(unrestored, regularisation_decrease=decrease))
        assert ip.Status(int(stuck.status)) is ip.Status.INFEASIBLE and float(stuck.violation) > 0.4
        assert not np.any(np.asarray(stuck.history)[: int(stuck.iterations), ip.HISTORY_COLUMNS.index("restoration")] == 1)
        if decrease == 1 / 3:
            assert np.abs(np.asarray(stuck.Z[:, 1:])).max() <= 1e-6


def test_slacks_start_at_the_rows_of_the_pushed_guess_and_every_slack_setting_reaches_the_same_optimum():
    """``Options.slack_start``: ``"pushed"`` (default) starts the slacks at the rows' values at the
    guess pushed inside its bounds (IPOPT's), ``"guess"`` at the guess itself; ``ipopt_slacks``
    (δ_w on the slacks) does not change the start. Every combination reaches the same optimum.
    Here the guess's u = 0.8 lies outside |u| ≤ 0.5: u² starts at 0.2401, not 0.64."""
    nlp = integrator(CAPPED, u_max=0.5, energy_cap=1.0)
    Z0 = jnp.zeros((K, 3)).at[:, 2].set(0.8)
    solutions = []
    for slack_start, ipopt_slacks in (("guess", False), ("pushed", False), ("pushed", True)):
        options = dataclasses.replace(OPTIONS, slack_start=slack_start, ipopt_slacks=ipopt_slacks)
        state = advance(nlp, ip.start(nlp, Z0, jnp.zeros(1), options), options, 0)  # start and first pass
        P = state.iterate.P
        rows_at_start = stagewise.residuals(nlp, P[0], P[1]).path_inequality * state.scaling[1][2]
        assert np.allclose(P[2], rows_at_start, rtol=1e-12) == (slack_start == "pushed")
        solutions.append(solve(nlp, Z0, jnp.zeros(1), options=options))
        assert ip.Status(int(solutions[-1].status)) is ip.Status.CONVERGED
    for other in solutions[1:]:
        np.testing.assert_allclose(other.Z, solutions[0].Z, atol=1e-6)
    assert ip.Options().slack_start == "pushed"
    with pytest.raises(ValueError, match="slack_start"):
        ip.Options(slack_start="pushed inside")


def test_the_first_pass_completes_the_start_at_the_starting_point():
    """``start`` evaluates nothing of the NLP: its state is unfinished (``FirstPass``), in unit
    scaling without a given one. ``advance``'s first pass, counting no iteration and made even
    when ``advance`` is asked for none, evaluates the residuals at the starting point (the guess
    pushed inside its bounds) and computes IPOPT's gradient-based scaling from the derivatives
    there, with the start's own ``max_gradient`` and ``bound_push``: the iterates are those of a
    start given that scaling, even when ``advance`` runs with ``iteration_options``."""
    nlp = integrator(CAPPED, u_max=0.5, energy_cap=1.0)
    Z0 = jnp.zeros((K, 3)).at[:, 2].set(0.8)
    options = dataclasses.replace(OPTIONS, max_gradient=0.5, bound_push=0.05)
    state = ip.start(nlp, Z0, jnp.zeros(1), options)
    assert bool(state.first_pass.pending) and bool(state.first_pass.scale) and float(state.scaling[0]) == 1.0
    P = state.iterate.P
    factors = scaling.scaling(stagewise.blocks(nlp, P[0], P[1]), options.max_gradient)
    assert float(factors[0]) < 1.0 and min(float(jnp.min(f, initial=1.0)) for f in factors[1]) < 1.0  # it matters
    given = ip.start(nlp, Z0, jnp.zeros(1), options, scaling=factors)
    assert bool(given.first_pass.pending) and not bool(given.first_pass.scale)
    iterating = ip.iteration_options(options)
    ours, theirs = advance(nlp, state, iterating, 3), advance(nlp, given, iterating, 3)
    assert int(ours.iterations) == 3 and not bool(ours.first_pass.pending)
    for a, b in zip(jax.tree.leaves((ours.scaling, ours.iterate, ours.history[:3])),
                    jax.tree.leaves((factors, theirs.iterate, theirs.history[:3]))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
    begun = advance(nlp, state, iterating, 0)  # the first pass alone
    assert not bool(begun.first_pass.pending) and int(begun.iterations) == 0
    at_start = stagewise.residuals(nlp, P[0], P[1])
    for a, b in zip(jax.tree.leaves((begun.residuals, begun.scaling)), jax.tree.leaves((at_start, factors))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(float(begun.violation), float(ip.violation(nlp, P[0], P[1])[0]), rtol=1e-12)
    assert bool(jnp.all(jnp.isnan(begun.history)))


# Per-knot Rosenbrock (1 − x)² + 100 (y − x²)², with a different box on x at each knot.
def _rosenbrock(a, z, theta, d):
    return (1 - z[0]) ** 2 + 100 * (z[1] - z[0] ** 2) ** 2 + 0.0 * d


def _theta_cost(a, theta):
    return 0.5 * jnp.sum(theta**2)


def _product(a, z, theta):
    return z[:1] * z[1:2]  # complementarity x y ≤ 0 with x, y ≥ 0


ROSENBROCK = StagewiseFunctions(_rosenbrock, _theta_cost, _no_path, _no_transition, _no_path, _no_transition)


def _unconstrained(functions, lower, upper, path_bounds=(EMPTY, EMPTY)):
    return StagewiseNLP(
        args=jnp.zeros(()), knot_data=jnp.zeros(lower.shape[0]), z_lower=lower, z_upper=upper,
        theta_lower=jnp.full(1, -jnp.inf), theta_upper=jnp.full(1, jnp.inf),
        path_lower=path_bounds[0], path_upper=path_bounds[1], transition_lower=EMPTY, transition_upper=EMPTY,
        functions=functions,
    )


def test_bound_constrained_rosenbrock():
    """x ≤ 0.5 → (0.5, 0.25); free → (1, 1); x ≥ 1.5 → (1.5, 2.25): from (−1.2, 1) at every knot."""
    lower = jnp.array([[-jnp.inf, -jnp.inf], [-jnp.inf, -jnp.inf], [1.5, -jnp.inf]])
    upper = jnp.array([[0.5, jnp.inf], [jnp.inf, jnp.inf], [jnp.inf, jnp.inf]])
    Z0 = jnp.tile(jnp.array([-1.2, 1.0]), (3, 1))
    solution = solve(_unconstrained(ROSENBROCK, lower, upper), Z0, jnp.ones(1), options=OPTIONS)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    expected = np.array([[0.5, 0.25], [1.0, 1.0], [1.5, 2.25]])
    assert np.abs(np.asarray(solution.Z) - expected).max() <= 1e-6
    assert abs(float(solution.theta[0])) <= 1e-8


def test_complementarity_problem():
    """min (x − 1)² + (y − 1)² s.t. x, y ≥ 0, x y ≤ 0 (degenerate, as the contact constraints
    are): from (1, 0.5) the solver ends at the vertex (1, 0) with objective 1."""

    def cost(a, z, theta, d):
        return (z[0] - 1) ** 2 + (z[1] - 1) ** 2 + 0.0 * d

    functions = StagewiseFunctions(cost, _theta_cost, _no_path, _no_transition, _product, _no_transition)
    nlp = _unconstrained(
        functions, jnp.zeros((2, 2)), jnp.full((2, 2), jnp.inf), (jnp.array([-jnp.inf]), jnp.zeros(1))
    )
    Z0 = jnp.array([[1.0, 0.5], [0.4, 1.0]])
    solution = solve(nlp, Z0, jnp.zeros(1), options=ip.Options(tolerance=1e-8, stationarity=1e-6))
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED, ip.Status(int(solution.status)).message
    Z = np.asarray(solution.Z)
    # The last barrier parameter's relaxation leaves the point near the vertex (seen: 5e-10 from it).
    assert np.abs(Z - np.array([[1.0, 0.0], [0.0, 1.0]])).max() <= 1e-8
    assert float(solution.violation) <= 1e-8
    assert abs(float(solution.objective) - 2.0) <= 1e-8




def _both_products(a, z, theta):
    return jnp.concatenate([z[:1] * z[1:2], -z[:1] * z[1:2]])  # x y ≤ 0 and −x y ≥ 0: one constraint twice


def _relaxable_complementarity():
    """min (x − 1)² + (y − 1)² s.t. x, y ≥ 0 and x y ≤ 0 written as an upper and as a lower bound,
    both marked for the relaxation homotopy (+1: the upper bound widened, −1: the lower)."""

    def cost(a, z, theta, d):
        return (z[0] - 1) ** 2 + (z[1] - 1) ** 2 + 0.0 * d

    functions = StagewiseFunctions(cost, _theta_cost, _no_path, _no_transition, _both_products, _no_transition)
    nlp = _unconstrained(functions, jnp.zeros((2, 2)), jnp.full((2, 2), jnp.inf),
                         (jnp.array([-jnp.inf, 0.0]), jnp.array([0.0, jnp.inf])))
    return dataclasses.replace(nlp, path_relaxation=jnp.array([1.0, -1.0]), transition_relaxation=EMPTY)


@pytest.mark.parametrize("relaxation", [0.0, 10.0])
def test_the_relaxation_homotopy_widens_the_marked_bounds_with_mu_and_ends_on_the_nlp_itself(relaxation):
    """Scholtes' relaxation driven by μ (``Options.relaxation``): while μ = 0.1 the marked rows
    admit x y ≤ σ = κ (μ − μ_floor), and the iterates move into that room towards (1, 1); the
    solve still ends on a vertex of the NLP itself (x y ≤ 0, violation ≤ 1e-8)."""
    nlp = _relaxable_complementarity()
    options = ip.Options(tolerance=1e-8, stationarity=1e-6, relaxation=relaxation)
    Z0 = jnp.array([[1.0, 0.5], [0.4, 1.0]])
    first = ip.advance(nlp, ip.start(nlp, Z0, jnp.zeros(1), options), options, until=1)
    assert float(first.mu) == 0.1  # the first barrier problem
    products = np.prod(np.asarray(first.iterate.P[0]), axis=1)
    if relaxation:  # σ = 10 (0.1 − 1e-6 / 11) ≈ 1: the step uses the room (seen: 0.57 and 0.52)
        assert products.min() >= 0.3
    else:  # seen: 0.066 and 0.033
        assert products.max() <= 0.1
    solution = ip.solve(nlp, Z0, jnp.zeros(1), options)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED, ip.Status(int(solution.status)).message
    assert float(solution.violation) <= 1e-8
    assert np.prod(np.asarray(solution.Z), axis=1).max() <= 1e-8
    assert abs(float(solution.objective) - 2.0) <= 1e-6


def test_vmap_over_initial_guesses_equals_a_loop():
    """Batched solves from different starting points: same answers as one solve at a time."""
    nlp = _unconstrained(ROSENBROCK, jnp.full((3, 2), -jnp.inf), jnp.full((3, 2), jnp.inf))
    guesses = jnp.stack([jnp.tile(jnp.array(p), (3, 1)) for p in ([-1.2, 1.0], [0.0, 0.0], [2.0, -1.0])])
    batched = jax.jit(jax.vmap(lambda Z0: ip.solve(nlp, Z0, jnp.ones(1), OPTIONS)))(guesses)
    for i in range(guesses.shape[0]):
        single = solve(nlp, guesses[i], jnp.ones(1), options=OPTIONS)
        assert int(batched.status[i]) == int(single.status) == ip.Status.CONVERGED
        assert int(batched.iterations[i]) == int(single.iterations)
        assert np.allclose(batched.Z[i], single.Z, atol=1e-12)
        assert np.abs(np.asarray(single.Z) - 1.0).max() <= 1e-6


def test_warm_start_from_a_solution_and_its_multipliers():
    nlp = integrator(CAPPED, energy_cap=0.01)
    cold = solve(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    options = ip.Options(tolerance=1e-9, stationarity=1e-9, barrier0=1e-9, bound_push=1e-9)
    warm = solve(nlp, cold.Z, cold.theta, options=options, multipliers=cold.multipliers,
                 bound_multipliers=cold.bound_multipliers)
    assert ip.Status(int(warm.status)) is ip.Status.CONVERGED
    assert int(warm.iterations) < int(cold.iterations)
    assert np.abs(np.asarray(warm.Z) - np.asarray(cold.Z)).max() <= 1e-6


def test_a_non_finite_value_stops_the_solve_with_the_last_finite_iterate():
    """√|x| has an infinite derivative at 0: the status says so, the numbers stay finite."""

    def cost(a, z, theta, d):
        return jnp.sqrt(jnp.abs(z[0])) + (z[1] - 1) ** 2 + 0.0 * d

    functions = StagewiseFunctions(cost, _theta_cost, _no_path, _no_transition, _no_path, _no_transition)
    nlp = _unconstrained(functions, jnp.full((2, 2), -jnp.inf), jnp.full((2, 2), jnp.inf))
    solution = solve(nlp, jnp.zeros((2, 2)), jnp.zeros(1), options=OPTIONS)
    assert ip.Status(int(solution.status)) is ip.Status.NAN
    leaves = jax.tree.leaves((solution.Z, solution.theta, solution.multipliers, solution.objective))
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)


def test_progress_callback_sees_every_iteration_record():
    records = []
    options = ip.Options(tolerance=1e-9, stationarity=1e-9, progress=lambda i, r: records.append((int(i), np.asarray(r))))
    solution = solve(integrator(), jnp.zeros((K, 3)), jnp.zeros(1), options=options)
    jax.effects_barrier()
    count = int(solution.iterations)
    assert [i for i, _ in records] == list(range(count))
    np.testing.assert_array_equal(np.stack([r for _, r in records]), np.asarray(solution.history)[:count])


def test_history_counts_the_block_solves_of_each_iteration():
    """Every step costs at least one block solve and at most one per refinement of each
    direction (the Newton step and its second-order corrections); the row of the converged
    iterate, where no step is taken, records none."""
    solution = solve(integrator(CAPPED, energy_cap=0.01), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    count = int(solution.iterations)
    solves = np.asarray(solution.history)[:count, ip.HISTORY_COLUMNS.index("linear_solves")]
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED and count > 3
    assert solves[-1] == 0
    assert np.all((solves[:-1] >= 1) & (solves[:-1] <= (1 + ip.REFINEMENT_STEPS) * (1 + ip.SOC_STEPS)))
    assert np.all(solves == np.round(solves))


def test_history_counts_the_factorisations_of_the_inertia_correction():
    """A convex problem factors once per iteration. Rosenbrock from (0, 1) at each of 3 knots has
    the Hessian diag(−398, 200) everywhere: the first iteration's attempts with δ_w = 0, 1e-4,
    1e-2, 1 and 100 each stop at block 0 (1 block each) and δ_w = 1e4 factors all 3 blocks:
    (5 + 3) / 3 factorisations."""
    convex = solve(integrator(), jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    history = np.asarray(convex.history)[: int(convex.iterations)]
    assert np.all(history[:, ip.HISTORY_COLUMNS.index("factorisations")] == 1.0)
    free = jnp.full((3, 2), jnp.inf)
    start = jnp.tile(jnp.array([0.0, 1.0]), (3, 1))
    solution = solve(_unconstrained(ROSENBROCK, -free, free), start, jnp.ones(1), options=OPTIONS)
    history = np.asarray(solution.history)[: int(solution.iterations)]
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    assert history[0, ip.HISTORY_COLUMNS.index("regularisation")] == 1e4
    assert history[0, ip.HISTORY_COLUMNS.index("factorisations")] == pytest.approx(8 / 3, rel=1e-15)
    assert np.all(np.round(3 * history[:, ip.HISTORY_COLUMNS.index("factorisations")]) >= 3)


@pytest.mark.parametrize("decrease", [ip.Options.regularisation_decrease, 1 / 3])
def test_the_inertia_correction_starts_from_the_last_regularisation_times_the_decrease(decrease):
    """Rosenbrock at (0, 1) (Hessian diag(−398, 200), halved by the cost scaling) needs δ_w > 199.
    With the last δ_w = 1e4, the first attempt after δ_w = 0 is 1e4 × the decrease, growing ×8:
    10 × 8² = 640 with the default 1e-3, 1e4 / 3 with IPOPT's κ_w⁻."""
    free = jnp.full((3, 2), jnp.inf)
    nlp = _unconstrained(ROSENBROCK, -free, free)
    options = dataclasses.replace(OPTIONS, regularisation_decrease=decrease)
    state = ip.start(nlp, jnp.tile(jnp.array([0.0, 1.0]), (3, 1)), jnp.ones(1), options)
    state = dataclasses.replace(state, regularisation=jnp.asarray(1e4))
    after = jax.jit(ip.advance, static_argnames="options")(nlp, state, options, 1)
    delta_w = float(after.history[0, ip.HISTORY_COLUMNS.index("regularisation")])
    assert delta_w == pytest.approx(640.0 if decrease == 1e-3 else 1e4 / 3, rel=1e-12)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="regularisation_decrease"):
            ip.Options(regularisation_decrease=bad)


def test_a_filter_entry_does_not_reject_the_point_it_was_made_from():
    """The filter's comparisons allow 10 ε of the entry (IPOPT's): at θ0 = 3.6e-6, φ0 = 546.4
    (walk-to-fly, iteration 2860) the entry (1 − 1e-5) θ0, φ0 − 1e-8 θ0 is φ0 in floating point,
    and an exact comparison rejected the point itself and every step near it: the solve stalled."""
    theta0, phi0 = 3.552522411638449e-06, 546.4147205020536
    entries_theta = jnp.array([1e4, (1 - 1e-5) * theta0, jnp.inf])
    entries_phi = jnp.array([-jnp.inf, phi0 - 1e-8 * theta0, jnp.inf])
    assert entries_phi[1] == phi0  # the margin is below φ0's rounding
    assert not ip.in_filter(theta0, phi0, entries_theta, entries_phi)
    assert ip.in_filter(2 * theta0, phi0 + 1e-9, entries_theta, entries_phi)  # worse in both
    assert not ip.in_filter(2 * theta0, phi0 - 1e-9, entries_theta, entries_phi)  # better in φ
    assert not ip.in_filter(0.5 * theta0, phi0 + 1.0, entries_theta, entries_phi)  # better in θ
    assert ip.in_filter(2e4, -1e30, entries_theta, entries_phi)  # beyond the envelope θ_max


advance = jax.jit(ip.advance, static_argnames="options")


def test_a_filter_that_rejects_every_trial_leaves_the_soft_restoration_step():
    """When the line search turns every trial down (here a filter entry at zero infeasibility,
    and no filter resets), IPOPT's soft restoration takes the Newton step to its
    fraction-to-boundary length if it lowers the primal–dual error, and puts the point it left
    in the filter; without it the step is rejected. The solve then converges to the optimum."""
    nlp = integrator(CAPPED, energy_cap=0.01)
    reference = solve(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options=OPTIONS)
    for soft_steps in (0, 10):
        options = dataclasses.replace(OPTIONS, max_filter_resets=0, max_soft_steps=soft_steps)
        state = advance(nlp, ip.start(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options), options, 2)
        f = state.filter
        blocked = dataclasses.replace(state, filter=dataclasses.replace(
            f, theta=f.theta.at[f.count].set(0.0), phi=f.phi.at[f.count].set(-jnp.inf), count=f.count + 1))
        after = advance(nlp, blocked, options, 3)
        step = float(after.history[2, ip.HISTORY_COLUMNS.index("step_length")])
        if soft_steps == 0:
            assert step == 0.0 and int(after.counters.rejections) == 1 and int(after.counters.soft_steps) == 0
            continue
        assert step > 0.0 and int(after.counters.rejections) == 0 and int(after.counters.soft_steps) == 1
        assert int(after.filter.count) == int(blocked.filter.count) + 1
        assert float(after.filter.theta[blocked.filter.count]) > 0.0  # the point left, with IPOPT's margins
        solution = ip.finish(nlp, advance(nlp, after, options, options.max_iterations))
        assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
        np.testing.assert_allclose(solution.Z, reference.Z, atol=1e-6)


def _without_refusal(state):
    return dataclasses.replace(state, soft=ip.SoftStep(state.soft.pending, state.soft.reference))


def test_a_soft_restoration_step_is_judged_at_the_next_iteration():
    """A pending soft-restoration step (``SoftStep``) is kept where the primal–dual error at its
    point is below 0.9999 of the reference, and turned down otherwise: the solve then goes on
    from the state it would have had without the step, as if the step had never been taken."""
    nlp = integrator(CAPPED, energy_cap=0.01)
    start = ip.start(nlp, jnp.zeros((K, 3)), jnp.zeros(1), OPTIONS)
    earlier, without = (advance(nlp, start, OPTIONS, n) for n in (2, 3))
    expected = advance(nlp, without, OPTIONS, 4)
    for reference, turned_down in ((0.0, True), (np.inf, False)):
        pending = dataclasses.replace(earlier, iterations=without.iterations, soft=ip.SoftStep(
            jnp.asarray(True), jnp.asarray(reference, without.soft.reference.dtype), _without_refusal(without)))
        after = advance(nlp, pending, OPTIONS, 4)
        assert int(after.iterations) == 4 and not bool(after.soft.pending)
        same = all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(after.iterate.P),
                                                        jax.tree.leaves(expected.iterate.P)))
        assert same == turned_down
        if turned_down:
            np.testing.assert_array_equal(np.asarray(after.history[3]), np.asarray(expected.history[3]))


def test_a_solve_stopped_on_a_pending_soft_restoration_step_judges_it_first():
    """Stopped at the iteration that took a soft-restoration step (``until``), ``advance`` keeps or
    undoes the step without taking another, so that a stopped solve (time budget, Ctrl-C,
    iteration cap) holds the iterate the whole solve has there, and going on from it is the
    whole solve."""
    nlp = integrator(CAPPED, energy_cap=0.01)
    start = ip.start(nlp, jnp.zeros((K, 3)), jnp.zeros(1), OPTIONS)
    earlier, without = (advance(nlp, start, OPTIONS, n) for n in (2, 3))
    for reference, turned_down in ((0.0, True), (np.inf, False)):
        pending = dataclasses.replace(earlier, iterations=without.iterations, soft=ip.SoftStep(
            jnp.asarray(True), jnp.asarray(reference, without.soft.reference.dtype), _without_refusal(without)))
        stopped = advance(nlp, pending, OPTIONS, 3)
        assert int(stopped.iterations) == 3 and not bool(stopped.soft.pending)
        held = without if turned_down else pending
        for a, b in zip(jax.tree.leaves(stopped.iterate), jax.tree.leaves(held.iterate)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        whole, sliced = advance(nlp, pending, OPTIONS, 5), advance(nlp, stopped, OPTIONS, 5)
        for a, b in zip(jax.tree.leaves(whole.iterate), jax.tree.leaves(sliced.iterate)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

