"""A primal–dual interior-point solver for stage-wise NLPs (``jaxmm.stagewise``).

    minimise f(z, θ)  s.t.  c(z, θ) = 0,  l_g ≤ g(z, θ) ≤ u_g,  z_lo ≤ z ≤ z_hi,  θ_lo ≤ θ ≤ θ_hi

Inequalities become equalities g − s = 0 with a slack s in [l_g, u_g]; every bound (variables
and slacks) is handled by a logarithmic barrier with primal–dual bound multipliers (``barrier``:
the barrier-parameter schedule, fraction-to-boundary rule and multiplier safeguards of IPOPT,
Wächter & Biegler 2006). The equality rows enter the Newton system through a primal–dual
augmented Lagrangian (stabilised SQP; Gill & Robinson 2013), whose condensed matrix is factored
by a block Cholesky that is also the inertia test (``newton``); W is the exact Hessian of the
Lagrangian. Steps are accepted by IPOPT's filter line search with second-order corrections and
soft restoration (``line_search``, ``filter``); when steps keep being rejected with the violation
above tolerance, a restoration phase (``restoration``) runs until a point acceptable to the filter
is found. Rows and the cost are scaled at the starting point as IPOPT's gradient-based scaling
does (``scaling``).

The algorithm: ``start`` (the ``State`` before the first iteration), ``iteration`` (one Newton
step: derivatives, system, factorisation, trials, update), ``advance`` (iterations in one
``lax.while_loop``, to the end or to an iteration count), ``finish`` (the ``Solution``) and
``solve`` (all three). Each iteration evaluates the NLP's derivatives, factors its matrix and
runs its block solves at one call site each, in either phase: the compiled program holds each
once. Everything can be jitted and vmapped; a non-finite value stops the solve with status
``NAN`` and the last finite iterate.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm import stagewise
from jaxmm.solver import barrier, filter as filters, line_search, newton, restoration, rows
from jaxmm.solver.filter import in_filter
from jaxmm.solver.options import (EQUALITIES, GROUPS, HISTORY_COLUMNS, INEQUALITIES, REFINEMENT_STEPS,  # noqa: F401
                                  SLACK_STARTS, SOC_STEPS, Options, Status, iteration_options)
from jaxmm.solver.scaling import outside, relaxed, scaled_problem, violation  # noqa: F401
from jaxmm.solver.scaling import scaling as gradient_scaling
from jaxmm.solver.state import Counters, FirstPass, Iterate, Multipliers, Solution, SoftStep, State  # noqa: F401
from jaxmm.solver.trees import all_finite, dot, l1, max_abs, select, tmap


def start(nlp, Z0, theta0, options=Options(), multipliers=None, bound_multipliers=None, scaling=None):
    """The solver's ``State`` before its first iteration from (Z0 (K, nz), θ0 (ng,)), pushed
    inside the bounds; the constraint multipliers warm-started with ``multipliers`` (a
    ``Multipliers``), the bound multipliers with ``bound_multipliers`` (both from a previous
    ``Solution``); ``scaling``: a previous ``Solution.scaling`` to solve in. The state is
    unfinished (``FirstPass``): ``advance``'s first pass evaluates the NLP at the starting point
    and, without a given scaling, computes IPOPT's gradient-based scaling there from the
    derivatives it evaluates, so that the NLP's functions and derivatives are compiled once, in
    the iteration. Only ``slack_start="guess"`` evaluates the NLP here (its rows at the guess)."""
    dtype = Z0.dtype
    b = barrier.bounds(nlp, (1.0, 1.0))  # (Z, θ)'s bounds do not depend on the scaling
    shapes = jax.eval_shape(stagewise.residuals, nlp, Z0, theta0)
    r0 = jax.tree.map(lambda x: jnp.zeros(x.shape, dtype), shapes)  # the first pass evaluates them
    rows_given = options.slack_start == "guess"
    rows0 = (r0.path_inequality, r0.transition_inequality)
    if rows_given:
        at_guess = stagewise.residuals(nlp, Z0, theta0)
        rows0 = (at_guess.path_inequality, at_guess.transition_inequality)
    Z0, theta0 = barrier.interior((Z0, theta0), b, options.bound_push)
    groups = tuple(getattr(r0, g) for g in GROUPS)
    factors = ((jnp.ones((), dtype), tuple(jnp.ones_like(g) for g in groups)) if scaling is None
               else (jnp.asarray(scaling[0], dtype), tuple(jnp.asarray(f, dtype) for f in scaling[1])))
    y0 = tuple(jnp.zeros_like(g) for g in groups) if multipliers is None else tuple(
        jnp.asarray(getattr(multipliers, g), dtype) for g in GROUPS)
    P0 = (Z0, theta0) + tuple(jnp.zeros_like(r) for r in rows0)
    ones = tuple(jnp.ones_like(p) for p in P0)
    zl0, zu0 = (ones, ones) if bound_multipliers is None else bound_multipliers
    zero, real = jnp.asarray(0), lambda x: jnp.asarray(x, dtype)
    state = State(
        iterate=Iterate(P0, y0, zl0, zu0), residuals=r0, mu=real(options.barrier0),
        regularisation=real(0.0), forced=real(0.0), filter=filters.empty(real(1e4)),
        counters=Counters(soft_steps=zero, rejections=zero, short_steps=zero, short_violation=real(0.0),
                          restoration_iterations=zero, barrier_updates=zero),
        iterations=zero, status=jnp.asarray(int(Status.RUNNING)), violation=real(0.0),
        stationarity=real(jnp.inf), history=jnp.full((options.max_iterations, len(HISTORY_COLUMNS)), jnp.nan, dtype),
        scaling=factors, theta_max=real(1e4), theta_min=real(1e-4), restoring=jnp.asarray(False),
        restoration_theta=real(0.0), soft=SoftStep(jnp.asarray(False), real(0.0)),
        first_pass=FirstPass(jnp.asarray(True), jnp.asarray(scaling is None), rows0, jnp.asarray(rows_given),
                             real(options.bound_push), real(options.max_gradient)),
    )
    state = dataclasses.replace(state, soft=SoftStep(state.soft.pending, state.soft.reference, state))
    # No weak types: a cold start (θ0 from Python floats) and a warm one must give the same avals,
    # so that one compiled ``advance`` serves both.
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x)), state)


def _relaxation(options, mu, cost_scale):
    """σ(μ) = κ_σ (μ − μ_floor) / cost factor of the relaxation homotopy (``Options.relaxation``),
    in the rows' units; None when off. μ / cost factor is the barrier parameter in the NLP's own
    cost units, so that one κ_σ serves tasks whose costs differ by orders of magnitude."""
    if not options.relaxation:
        return None
    return options.relaxation * jnp.maximum(mu - options.barrier_floor, 0.0) / cost_scale


def _in_scaling(nlp, state, factors, y, sigma):
    """``state`` (at the starting point, with its residuals there) in the scaling ``factors``
    (cost factor, per-row factors): the slacks at the rows of ``state.first_pass`` pushed inside
    their scaled bounds (the primal (Z, θ) is inside already, and the push leaves it), the
    multipliers ``y`` (the NLP's units) scaled, the bound multipliers kept where there is a
    bound, and the filter's envelope from the scaled residuals (IPOPT's θ_max = 10⁴ max(1, θ(x₀)),
    θ_min = 10⁻⁴ of it); σ: the relaxation of the marked rows (``Options.relaxation``)."""
    problem = scaled_problem(nlp, factors, sigma)
    cost_scale, row_scale, b = problem.cost_scale, problem.row_scale, problem.bounds
    it, start_rows = state.iterate, relaxed(nlp, *state.first_pass.rows, sigma)
    P = barrier.interior((it.P[0], it.P[1], start_rows[0] * row_scale[2], start_rows[1] * row_scale[3]), b,
                         state.first_pass.bound_push)
    y = tuple(cost_scale * v / s for v, s in zip(y, row_scale))
    zl = tmap(lambda v, m: jnp.where(m, v, 0.0), it.zl, b.has_lower)
    zu = tmap(lambda v, m: jnp.where(m, v, 0.0), it.zu, b.has_upper)
    envelope = jnp.maximum(1.0, l1(problem.constraints(P, state.residuals)))
    return dataclasses.replace(
        state, iterate=Iterate(P, y, zl, zu), scaling=factors, filter=filters.empty(1e4 * envelope),
        theta_max=1e4 * envelope, theta_min=1e-4 * envelope)


@dataclasses.dataclass(frozen=True)
class Context:
    """What every iteration of one solve shares: the ``scaling.ScaledProblem``, the fixed
    variables' ``newton.Masks``, the rows' supports and the coupled columns (static sparsity),
    the options."""

    problem: object
    masks: newton.Masks
    supports: dict
    coupled: tuple | None
    options: Options

    @property
    def K(self):
        return self.masks.free_z.shape[0]


def context(nlp, state, options):
    """The ``Context`` of a solve of ``nlp`` in the scaling of ``state``."""
    problem = scaled_problem(nlp, state.scaling, _relaxation(options, state.mu, state.scaling[0]))
    supports = stagewise.row_supports(nlp)
    return Context(problem, newton.masks(problem.bounds, state.iterate.P[0].dtype), supports,
                   rows.coupled_columns(supports), options)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Optimality:
    """The optimality measures at the iterate (IPOPT's section 2.1): grad, the Lagrangian's
    gradient per primal leaf (bounds apart); dual, the dual infeasibility; dual_error and
    primal_error; s_c, the complementarity's scaling; error0, the optimality error E₀ without
    the violation (``Options.stationarity``)."""

    grad: tuple
    dual: tuple
    dual_error: jax.Array
    primal_error: jax.Array
    s_c: jax.Array
    error0: jax.Array


def optimality(ctx, state, B, J, c, dl, du):
    """The ``Optimality`` of ``state``'s iterate, with the blocks B, rows J, residuals c and
    distances (dl, du) there."""
    it, b, K = state.iterate, ctx.problem.bounds, ctx.K
    y, zl, zu = it.y, it.zl, it.zu
    gz, gt = ctx.problem.cost_scale * B.cost_z, ctx.problem.cost_scale * B.cost_theta
    for r, yi in zip(J, y):
        pz, pt = rows.pull(r, yi, K)
        gz, gt = gz + pz, gt + pt
    grad = (gz, gt, -y[2], -y[3])
    dual = tmap(lambda g, a, c_, f: jnp.where(f, g - a + c_, 0.0), grad, zl, zu, b.free)
    n_mult = sum(v.size for v in y) + sum(v.size for v in zl) + sum(v.size for v in zu)
    n_var = sum(p.size for p in it.P)
    s_d = jnp.maximum(100.0, l1(y + zl + zu) / max(n_mult, 1)) / 100.0
    s_c = jnp.maximum(100.0, l1(zl + zu) / max(2 * n_var, 1)) / 100.0
    dual_error = max_abs(dual) / s_d
    error0 = jnp.maximum(dual_error, max_abs(barrier.complementarity(dl, du, zl, zu, 0.0, b)) / s_c)
    return Optimality(grad, dual, dual_error, max_abs(c), s_c, error0)


def barrier_update(ctx, state, o, dl, du):
    """(μ, the number of decreases): IPOPT's monotone update, μ ← max(floor, min(κ_μ μ, μ^θ_μ))
    as long as the barrier problem is solved to κ_ε μ (none in the restoration phase)."""
    options, it = ctx.options, state.iterate
    floor = options.barrier_floor

    def solved(carry):
        mu, _ = carry
        complementarity = max_abs(barrier.complementarity(dl, du, it.zl, it.zu, mu, ctx.problem.bounds)) / o.s_c
        return (~state.restoring & (jnp.maximum(jnp.maximum(o.dual_error, o.primal_error), complementarity)
                                    <= options.barrier_tolerance_factor * mu) & (mu > floor))

    def decrease(carry):
        mu, count = carry
        return jnp.maximum(floor, jnp.minimum(options.barrier_factor * mu, mu**options.barrier_power)), count + 1

    return jax.lax.while_loop(solved, decrease, (state.mu, jnp.asarray(0)))


@dataclasses.dataclass(frozen=True)
class Step:
    """One iteration's quantities that its update reads (traced values, not a pytree): c, the
    scaled residuals at the iterate and f_now its scaled cost; dl, du, the distances to the
    bounds; optimality (``Optimality``); mu, the barrier parameter after the update, updates its
    decreases, mu_step the barrier parameter of the step (the restoration phase's μ_R);
    filter and soft_steps after the update's reset; crawling (short steps that no longer cut
    the violation), converged; delta_w, factored, work (the inertia correction's); zeta, the
    restoration phase's damping; search, the ``line_search.Search``; theta0, phi0, the filter's
    measures at the iterate."""

    c: tuple
    f_now: jax.Array
    dl: tuple
    du: tuple
    optimality: Optimality
    mu: jax.Array
    updates: jax.Array
    mu_step: jax.Array
    filter: filters.Filter
    soft_steps: jax.Array
    crawling: jax.Array
    converged: jax.Array
    delta_w: jax.Array
    factored: jax.Array
    work: jax.Array
    zeta: jax.Array
    search: line_search.Search
    theta0: jax.Array
    phi0: jax.Array


def _lagrangian_hessian(ctx, state, B):
    """Blocks (D, L, B, C) of the scaled Lagrangian's Hessian, L a ``stagewise.Coupling``: the
    cost's plus the constraints' curvature at the multipliers (from the blocks' kinematic
    curvature, ``stagewise``)."""
    problem, it = ctx.problem, state.iterate
    D, L, Bk, C = stagewise.constraint_curvature(problem.nlp, it.P[0], it.P[1],
                                                 *(yi * s for yi, s in zip(it.y, problem.row_scale)),
                                                 path_linearisation=B.path_linearisation, compact=True)
    # The knot costs couple no two knots: nothing is added to L (a pass over its (K − 1, nz, nz)).
    cs = problem.cost_scale
    return B.cost_zz.added_to(D, cs), L, Bk + cs * B.cost_ztheta, C + cs * B.cost_thetatheta


def _system(ctx, state, B, J, sigma, D2, zeta):
    """The Newton system's parts as functions of δ_w: (system_at(δ) → ``newton.System``,
    blocks_at(δ) → the blocks to factor, the fixed variables held out by the factorisation
    (``ctx.masks``), diagonal_at(δ) → the diagonal shifts). In the
    barrier problem the Lagrangian's Hessian + Σ + δ_w, the rows weighted 1/δ_c (equalities)
    and 1/(1/(σ_s + δ_s) + δ_c) (inequalities, slacks eliminated); in the restoration phase
    JᵀJ + Σ + ζ D², the rows weighted 1 and 1/(1/(σ_s + ζ D²) + 1) (Gauss–Newton)."""
    options, problem, m, K = ctx.options, ctx.problem, ctx.masks, ctx.K
    restoring = state.restoring
    base = jax.lax.cond(restoring, lambda: _zero_hessian(ctx, B), lambda: _lagrangian_hessian(ctx, state, B))
    # The condensed matrix needs L's blocks; the refinement's products with W take the coupling
    # as it is (two passes over (K − 1, nz, nz) blocks fewer per residual).
    dense = (base[0], base[1].dense()) + base[2:]
    reg = jnp.where(restoring, 1.0, options.dual_regularisation)

    def extra(delta):
        return tmap(lambda d: jnp.where(restoring, zeta * d, delta), D2)

    def slack_terms(delta):
        """(1/(σ_s + δ_s) per slack, σ_s + δ_s, every row's weight in the condensed matrix)."""
        diagonal = tmap(lambda s, e: s + e, sigma[2:], extra(delta)[2:])
        inv = tuple(jnp.where(s > 0, 1.0 / jnp.where(s > 0, d, 1.0), 0.0) for s, d in zip(sigma[2:], diagonal))
        weight_g = tuple(jnp.where(a, 1.0 / (i + reg), 0.0) for i, a in zip(inv, problem.active))
        return inv, diagonal, (jnp.full_like(J[0].jz[..., 0], 1.0 / reg), jnp.full_like(J[1].jz[..., 0], 1.0 / reg)) + weight_g

    # With ``ipopt_slacks`` δ_w regularises the slacks too (IPOPT's δ_s = δ_w): their 1/σ, and so
    # the inequality rows' weights in the condensed matrix, depend on δ_w.
    if options.ipopt_slacks:
        equalities = rows.grams(J[:2], slack_terms(0.0)[2][:2], K, into=dense)
        blocks_at = lambda delta: rows.grams(J[2:], slack_terms(delta)[2][2:], K, into=equalities)  # noqa: E731
    else:
        unshifted = rows.grams(J, slack_terms(0.0)[2], K, into=dense)
        blocks_at = lambda delta: unshifted  # noqa: E731

    def diagonal_at(delta):
        e = extra(delta)
        return m.free_z * (sigma[0] + e[0]), m.free_theta * (sigma[1] + e[1])

    def system_at(delta):
        delta_s = delta if options.ipopt_slacks else 0.0
        inv, slack_diagonal, weights = slack_terms(delta_s)
        e = extra(delta)
        return newton.System(J=J, weights=weights, inv_sigma=inv, hessian=base,
                             diagonal=(sigma[0] + e[0], sigma[1] + e[1]), slack_diagonal=slack_diagonal,
                             active=problem.active, masks=m)

    return system_at, blocks_at, diagonal_at


def _zero_hessian(ctx, B):
    """Zero blocks (D, L, B, C) of ``_lagrangian_hessian``'s shapes (the restoration phase's W)."""
    K, nz, ng, dtype = ctx.K, B.cost_z.shape[-1], B.cost_thetatheta.shape[-1], B.cost_z.dtype
    return (jnp.zeros((K, nz, nz), dtype), stagewise.zero_coupling(ctx.problem.nlp, K, nz, dtype),
            jnp.zeros((K, nz, ng), dtype), jnp.zeros((ng, ng), dtype))


def iteration(ctx, state, judge_only=False):
    """One iteration from ``state``: the NLP's derivatives, the optimality measures and the
    barrier update, the Newton system factored with inertia correction, the trials of the line
    search, and the update (the barrier problem's, or the restoration phase's). Returns the new
    ``State``. ``judge_only`` (a bool, traced or not): only keep or undo a pending
    soft-restoration step, taking no new one (a solve stopping at its iteration cap)."""
    problem, b, it = ctx.problem, ctx.problem.bounds, state.iterate
    P, y = it.P, it.y
    # The path multipliers let the blocks carry the path Hessian's kinematic curvature, computed
    # with their Jacobian (the Lagrangian's curvature uses the same multipliers).
    B = stagewise.blocks(problem.nlp, P[0], P[1], path_multipliers=(y[0] * problem.row_scale[0],
                                                                   y[2] * problem.row_scale[2]))
    J = newton.jacobian_rows(problem, B, ctx.supports)
    c = problem.constraints(P, state.residuals)
    dl, du = barrier.distances(P, b)
    o = optimality(ctx, state, B, J, c, dl, du)
    # A soft-restoration step is kept if the primal–dual error here beats the one it started from.
    error = _soft_error(ctx, it, o.dual, c, dl, du, state.mu)
    refuse = state.soft.pending & ~(error <= 0.9999 * state.soft.reference)
    # Both outcomes are computed and one is selected: a conditional around the iteration would
    # take the blocks (megabytes) as operands, which XLA copies into its branch.
    judge_only, pending = jnp.asarray(judge_only), state.first_pass.pending
    kept = dataclasses.replace(state, soft=SoftStep(jnp.zeros_like(state.soft.pending), state.soft.reference,
                                                    state.soft.refused))
    stepped, evaluated = _newton_iteration(ctx, state, B, J, c, dl, du, o, ~refuse & ~judge_only & ~pending)
    after = select(refuse, _refused(ctx, state, refuse), select(judge_only | pending, kept, stepped))
    return _first_pass(ctx, state, B, after, evaluated)


def _first_pass(ctx, state, B, after, r0):
    """``after`` (the iteration's new state), unless ``state`` is the unfinished state of
    ``start`` (``FirstPass``): then this pass only completes it, counting no iteration, from the
    residuals r0 that the line search evaluated at the starting point and, without a given
    scaling, IPOPT's gradient-based scaling from the blocks B there. Only the leaves that the
    pass sets are selected."""
    first, nlp = state.first_pass, ctx.problem.nlp
    # IPOPT's gradient-based scaling reads every Jacobian entry: computed in the first pass
    # alone, not computed and discarded in every iteration (≈ 5 ms on take-off N = 70).
    factors = jax.lax.cond(first.pending & first.scale, lambda: gradient_scaling(B, first.max_gradient),
                           lambda: state.scaling)
    sigma = _relaxation(ctx.options, state.mu, factors[0])
    v0, _ = violation(nlp, state.iterate.P[0], state.iterate.P[1], r0, sigma)
    rows = select(first.rows_given, first.rows, (r0.path_inequality, r0.transition_inequality))
    begun = dataclasses.replace(state, residuals=r0, violation=v0,
                                counters=dataclasses.replace(state.counters, short_violation=v0),
                                first_pass=dataclasses.replace(first, rows=rows))
    scaled = _in_scaling(nlp, begun, factors, state.iterate.y, sigma)
    fields = ("iterate", "residuals", "violation", "counters", "scaling", "filter", "theta_max", "theta_min")
    chosen = select(first.pending, tuple(getattr(scaled, f) for f in fields), tuple(getattr(after, f) for f in fields))
    return dataclasses.replace(after, **dict(zip(fields, chosen)), first_pass=dataclasses.replace(
        after.first_pass, pending=jnp.zeros_like(first.pending)))


def _report(ctx, when, k, row):
    """Show history row ``row`` of iteration k to ``options.progress``, where ``when``."""
    if ctx.options.progress is not None:
        jax.lax.cond(when, lambda: jax.debug.callback(ctx.options.progress, k, row), lambda: None)


def _refused(ctx, state, report):
    """The state had the soft-restoration step that led to ``state`` been turned down (the
    iteration that took it, counted once); its history row is shown again where ``report``."""
    refused = state.soft.refused
    _report(ctx, report, refused.iterations - 1, refused.history[refused.iterations - 1])
    done = SoftStep(jnp.zeros_like(state.soft.pending), state.soft.reference, refused)
    return dataclasses.replace(refused, soft=done)


def _newton_iteration(ctx, state, B, J, c, dl, du, o, report):
    """The rest of ``iteration`` from the blocks B, rows J, residuals c, distances (dl, du) and
    ``Optimality`` o at the iterate: (the new ``State``, the NLP's residuals at the line search's
    last trial, which in the first pass (``FirstPass``) is the iterate itself); its history row is
    shown to the progress callback where ``report``."""
    problem, options, b = ctx.problem, ctx.options, ctx.problem.bounds
    it, restoring = state.iterate, state.restoring
    P, zl, zu = it.P, it.zl, it.zu
    # With the relaxation homotopy the state's violation is the relaxed NLP's; convergence is the NLP's own.
    feasible = violation(problem.nlp, P[0], P[1], state.residuals)[0] if options.relaxation else state.violation
    converged = ~restoring & (o.error0 <= options.stationarity) & (feasible <= options.tolerance)
    # Short steps that no longer cut the violation: restoration from here, without a step.
    crawling = (~restoring & (options.max_short_steps > 0) & (options.max_restoration_iterations > 0)
                & (state.counters.short_steps >= options.max_short_steps) & (state.violation > options.tolerance)
                & ~converged)
    mu, updates = barrier_update(ctx, state, o, dl, du)
    reset = updates > 0
    if options.relaxation:  # the step solves the barrier problem at the new μ, with its σ(μ)
        problem = dataclasses.replace(problem, sigma=_relaxation(options, mu, problem.cost_scale))
        ctx = dataclasses.replace(ctx, problem=problem)
        c = problem.constraints(P, state.residuals)
    filter_now = filters.reset(state.filter, state.theta_max, reset, 0)
    mu_r, zeta, D2 = restoration.terms(state, c, b)
    mu_step = jnp.where(restoring, mu_r, mu)
    tau = jnp.maximum(0.99, 1.0 - mu_step)
    sigma, bgrad = barrier.terms(dl, du, zl, zu, mu_step, b)
    rx = tmap(lambda g, bg, f: jnp.where(restoring, jnp.where(f, bg, 0.0), g + bg), o.grad, bgrad, b.free)
    system_at, blocks_at, diagonal_at = _system(ctx, state, B, J, sigma, D2, zeta)
    # Inertia correction (IPOPT's rule but for the decrease): δ_w = 0 first, then from the last
    # δ_w × regularisation_decrease, ×8. IPOPT's third of the last δ_w kept take-off's δ_w at
    # 1.4–4100× the least that factors (median 5×; the need swings by 1000× between
    # iterations): 702 iterations against 243 with 1e-3 (docs/design-decisions.md, κ_w⁻).
    delta_w, chol, factored, work = newton.factor(
        blocks_at, diagonal_at, jnp.where(restoring, 0.0, state.forced),
        lambda delta: newton.next_regularisation(delta, state.regularisation, options.regularisation_decrease),
        ~restoring & ~state.first_pass.pending, 1e40, ctx.K, ctx.coupled, ctx.masks)  # one attempt in the first pass
    system = system_at(delta_w)
    limit = jnp.where(restoring, 1, 1 + REFINEMENT_STEPS)

    def direction(cq, needed):
        rhs = ((-rx[0], -rx[1]), (-rx[2], -rx[3]), tuple(-v for v in cq))
        (dx, ds, dy), solves = newton.refined_solve(chol, system, rhs, jnp.where(needed, limit, 0))
        dP = dx + ds
        dzl, dzu, alpha_max, alpha_z = barrier.bound_steps(dl, du, zl, zu, dP, mu_step, tau, b)
        return line_search.Direction(dP, dy, dzl, dzu, alpha_max, alpha_z, dx, ds, solves)

    cs = problem.cost_scale
    slope_of = lambda d: jax.lax.cond(  # noqa: E731
        restoring, lambda: restoration.slope(c, J, d, problem.active, bgrad),
        lambda: dot((cs * B.cost_z, cs * B.cost_theta), d.dP[:2]) + dot(bgrad, d.dP))
    log_sum = barrier.log_sum(P, b)
    theta0, phi0, psi0 = l1(c), cs * state.residuals.cost - mu * log_sum, restoration.measure(c, log_sum, mu_r)
    rounding = filters.rounding(P[0].dtype)

    def judge(alpha_judge, alpha, trial, theta, slope):
        Pt, f, ct = trial
        logs = barrier.log_sum(Pt, b)
        accepted, f_type, by_filter = line_search.filter_acceptance(
            alpha_judge, theta, f - mu * logs, theta0, phi0, slope, state.theta_min,
            lambda th, ph: in_filter(th, ph, filter_now.theta, filter_now.phi), rounding)
        psi = restoration.measure(ct, logs, mu_r)
        sufficient = jnp.isfinite(psi) & (psi - psi0 - 1e-4 * alpha * slope <= rounding * jnp.abs(psi0))
        return (jnp.where(restoring, sufficient, accepted), ~restoring & f_type, ~restoring & by_filter)

    soft_steps = jnp.where(reset, 0, state.counters.soft_steps)
    pending = state.first_pass.pending
    search = line_search.search(P, c, state.residuals, direction, problem.evaluate, judge, slope_of, l1, restoring,
                                factored & ~crawling & ~pending, options.line_search_steps,
                                ~restoring & (soft_steps < options.max_soft_steps), evaluate_only=pending)
    step = Step(c=c, f_now=cs * state.residuals.cost, dl=dl, du=du, optimality=o, mu=mu, updates=updates,
                mu_step=mu_step, filter=filter_now, soft_steps=soft_steps,
                crawling=crawling, converged=converged, delta_w=delta_w, factored=factored, work=work, zeta=zeta,
                search=search, theta0=theta0, phi0=phi0)
    (new, record), (refused, refused_record), soft = jax.lax.cond(
        restoring, lambda: (restoration.outcome(problem, options, state, step),) * 2 + (jnp.asarray(False),),
        lambda: _outcome(ctx, state, step))
    k = state.iterations
    new = dataclasses.replace(new, history=state.history.at[k].set(record))
    refused = dataclasses.replace(refused, history=state.history.at[k].set(refused_record), iterations=k + 1,
                                  soft=SoftStep(jnp.asarray(False), state.soft.reference))
    # A non-finite derivative or step stops the solve even where the line search rejected it.
    searched = factored & ~crawling
    finite = all_finite((new.iterate, o.dual)) & (~searched | all_finite(search.newton.dP))
    new = dataclasses.replace(new, soft=SoftStep(soft & finite, _soft_reference(ctx, state, step), refused))
    new = select(finite, new, state)
    _report(ctx, report, k, new.history[k])  # the row the history keeps for this iteration
    new = dataclasses.replace(new, status=jnp.where(finite, new.status, int(Status.NAN)), iterations=k + 1)
    return new, search.last.r


def _primal_dual_error(dual, c, complementarity):
    """The barrier problem's primal–dual error, IPOPT's soft-restoration measure: mean |dual
    infeasibility| + mean |residual| + mean |distance · z − μ|."""
    return sum(l1(tree) / max(sum(v.size for v in tree), 1) for tree in (dual, c, complementarity))


def _soft_error(ctx, it, dual, c, dl, du, mu):
    """The barrier problem's primal–dual error (μ) at the ``Iterate`` it, whose dual
    infeasibility is ``dual`` (``Optimality.dual``), residuals c and distances (dl, du): the
    measure of IPOPT's soft restoration (``SoftStep``). The slacks' dual rows count only the
    rows that are active (``ScaledProblem.active``), as the slacks enter the residuals."""
    problem, b = ctx.problem, ctx.problem.bounds
    slack_dual = tuple(jnp.where(f, -yi * a - p + q, 0.0) for yi, a, p, q, f in
                       zip(it.y[2:], problem.active, it.zl[2:], it.zu[2:], b.free[2:]))
    return _primal_dual_error(dual[:2] + slack_dual, c, barrier.complementarity(dl, du, it.zl, it.zu, mu, b))


def _soft_reference(ctx, state, step):
    """The primal–dual error at the iterate, which a soft-restoration step from it must lower to
    0.9999 of (IPOPT's soft restoration; ``SoftStep``)."""
    return _soft_error(ctx, state.iterate, step.optimality.dual, step.c, step.dl, step.du, step.mu)


def _outcome(ctx, state, step):
    """The barrier problem's update after one iteration: ((state, history row) with the
    soft-restoration point where the search ended on one, (state, row) had it been turned
    down, whether it is pending (``SoftStep``))."""
    soft = step.search.soft & ~step.converged
    return _update(ctx, state, step, soft), _update(ctx, state, step, jnp.asarray(False)), soft


def _update(ctx, state, step, soft):
    """The state after one iteration of the barrier problem (IPOPT's update: the accepted step
    or, where ``soft``, the soft-restoration point; the filter, the rejection counters and the
    switch to the restoration phase) and its history row."""
    problem, options, b, it, s = ctx.problem, ctx.options, ctx.problem.bounds, state.iterate, step.search
    accepted = s.accepted & step.factored & ~step.crawling
    d = select(s.corrected, s.correction, s.newton)  # the corrected step replaces the Newton step
    P_soft, r_soft = s.last.P, s.last.r
    alpha_soft = jnp.minimum(s.newton.alpha_max, s.newton.alpha_z)
    length = jnp.where(accepted, s.last.alpha, jnp.where(soft, alpha_soft, 0.0))
    length_z = jnp.where(accepted, d.alpha_z, jnp.where(soft, alpha_soft, 0.0))
    P_new, r_new = select(accepted, (s.last.P, s.last.r), select(soft, (P_soft, r_soft), (it.P, state.residuals)))
    y_new = tmap(lambda v, dv: v + length * dv, it.y, d.dy)
    zl_new, zu_new = barrier.safeguard(tmap(lambda v, dv: v + length_z * dv, it.zl, d.dzl),
                                       tmap(lambda v, dv: v + length_z * dv, it.zu, d.dzu), P_new, step.mu, b)
    # The filter grows after every accepted step that was not an Armijo (f-type) step, and with
    # the iterate a soft restoration starts from; no step accepted, but one the filter alone
    # turned down (the iterate has wandered into a pocket its own history fences in): the filter
    # is emptied and the step retried (IPOPT's filter reset heuristic).
    f = filters.augment(step.filter, step.theta0, step.phi0, (accepted & ~s.f_type) | (soft & (step.soft_steps == 0)))
    unblock = (step.factored & ~accepted & ~soft & ~step.crawling & s.blocked
               & (f.resets < options.max_filter_resets))
    f = filters.reset(f, state.theta_max, unblock, f.resets + 1)
    moved = accepted | soft
    counters = state.counters
    # Steps rejected max_rejections times in a row, each retried with more regularisation, with
    # the violation above tolerance: IPOPT's restoration phase, from here.
    restore = step.crawling | (~moved & ~unblock & (counters.rejections + 1 >= options.max_rejections)
                               & (state.violation > options.tolerance) & (options.max_restoration_iterations > 0))
    f = filters.augment(f, step.theta0, step.phi0, restore)
    rejections = jnp.where(moved | unblock | restore, 0, counters.rejections + 1)
    v_new, _ = problem.violation(P_new, r_new)
    short = (length < options.short_step) & ~restore
    short_violation = jnp.where(short & (counters.short_steps == 0), state.violation, counters.short_violation)
    factorisations = step.work.astype(v_new.dtype) / ctx.K
    status = jnp.where(
        step.converged, int(Status.CONVERGED),
        jnp.where(rejections < options.max_rejections, int(Status.RUNNING),
                  jnp.where(state.violation > options.tolerance, int(Status.INFEASIBLE), int(Status.STALLED))))
    new = dataclasses.replace(
        state, iterate=Iterate(P_new, y_new, zl_new, zu_new), residuals=r_new, mu=step.mu,
        regularisation=jnp.where(step.delta_w > 0, step.delta_w, state.regularisation),
        # A rejected step is retried from a more heavily regularised (shorter, steeper) one.
        forced=jnp.where(moved | unblock | restore, 0.0, jnp.maximum(step.delta_w * 100.0, 1e-4)),
        filter=f, counters=Counters(
            soft_steps=jnp.where(soft, step.soft_steps + 1, jnp.where(accepted, 0, step.soft_steps)),
            rejections=rejections, short_steps=jnp.where(short & (v_new > 0.9 * short_violation), counters.short_steps + 1, 0),
            short_violation=short_violation, restoration_iterations=jnp.zeros_like(counters.restoration_iterations),
            barrier_updates=counters.barrier_updates + step.updates),
        status=status, violation=v_new, stationarity=step.optimality.error0, restoring=restore,
        restoration_theta=jnp.where(restore, step.theta0, state.restoration_theta))
    record = jnp.stack([r_new.cost, v_new, step.optimality.error0, step.mu, length, step.delta_w, s.solves, 0.0,
                        factorisations])
    # Converged: keep the point where the test held, not the step taken from it.
    kept = dataclasses.replace(state, status=status, stationarity=step.optimality.error0)
    converged_record = jnp.stack([state.residuals.cost, state.violation, step.optimality.error0, step.mu, 0.0,
                                  step.delta_w, 0.0, 0.0, factorisations])
    return select(step.converged, (kept, converged_record), (new, record))


def advance(nlp, state, options=Options(), until=None):
    """Iterate from ``state`` until the solve stops (converged, infeasible, stalled, NaN) or
    ``state.iterations`` reaches ``until`` (a traced int is fine: one compilation serves every
    count; default and cap: options.max_iterations). Returns the new ``State``.

    ``advance(nlp, advance(nlp, s, o, k), o)`` is ``advance(nlp, s, o)``: a solve can be run in
    slices, with the host deciding between them whether to go on (``solve.solve_task``'s time budget
    and Ctrl-C). A soft-restoration step pending at ``until`` is judged before returning (kept
    or undone, ``iteration``'s ``judge_only``), so that a stopped solve reports the iterate the
    whole solve has at that iteration."""
    limit = options.max_iterations if until is None else jnp.minimum(until, options.max_iterations)

    def running(s):
        return (s.status == int(Status.RUNNING)) & ((s.iterations < limit) | s.soft.pending | s.first_pass.pending)

    # The context is rebuilt from each state's scaling: the first pass may fix it (``FirstPass``).
    return jax.lax.while_loop(running, lambda s: iteration(context(nlp, s, options), s, s.iterations >= limit), state)


def finish(nlp, state, stopped=Status.MAX_ITERATIONS):
    """The ``Solution`` at ``state``; a solve still running is reported with status ``stopped``
    (an int, traced or not: ``MAX_ITERATIONS``, ``INTERRUPTED``, ``TIME_LIMIT``)."""
    cost_scale, row_scale = state.scaling[0], tuple(state.scaling[1])
    status = jnp.where(state.status == int(Status.RUNNING), jnp.asarray(stopped, state.status.dtype), state.status)
    it = state.iterate
    Z, theta = it.P[0], it.P[1]
    v, per_group = violation(nlp, Z, theta, state.residuals)  # the residuals the state carries, at (Z, θ)
    return Solution(
        Z=Z, theta=theta,
        multipliers=Multipliers(**{g: yi * s / cost_scale for g, yi, s in zip(GROUPS, it.y, row_scale)}),
        status=status, objective=state.residuals.cost, violation=v,
        violation_per_group=per_group, stationarity=state.stationarity, iterations=state.iterations,
        barrier_updates=state.counters.barrier_updates, history=state.history, bound_multipliers=(it.zl, it.zu),
        slacks=(it.P[2], it.P[3]), scaling=(cost_scale, row_scale),
    )


def solve(nlp, Z0, theta0, options=Options(), multipliers=None, bound_multipliers=None, scaling=None):
    """Minimise the stage-wise NLP from (Z0 (K, nz), θ0 (ng,)): ``start``, ``advance`` to the
    end, ``finish``. ``multipliers``, ``bound_multipliers``: a warm start from a previous
    ``Solution``; ``scaling``: a previous ``Solution.scaling`` to solve in (default: computed
    at the starting point). Keeping the scaling of a previous solve makes the answers to nearby
    problems differ only through the problem: the barrier problem at μ > 0 depends on the cost
    factor.

    Jittable and vmappable (options are static): ``jax.jit(solve, static_argnames="options")``.
    Returns a ``Solution``.
    """
    state = start(nlp, Z0, theta0, options, multipliers, bound_multipliers, scaling)
    return finish(nlp, advance(nlp, state, options))
