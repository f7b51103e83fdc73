"""A primal–dual interior-point solver for stage-wise NLPs (``jaxmm.stagewise``).

    minimise f(z, θ)  s.t.  c(z, θ) = 0,  l_g ≤ g(z, θ) ≤ u_g,  z_lo ≤ z ≤ z_hi,  θ_lo ≤ θ ≤ θ_hi

Inequalities become equalities g − s = 0 with a slack s in [l_g, u_g]; every bound (variables
and slacks) is handled by a logarithmic barrier with primal–dual bound multipliers (Fiacco &
McCormick; the barrier-parameter schedule, fraction-to-boundary rule, multiplier safeguards
and filter line search of IPOPT, Wächter & Biegler 2006). The equality rows enter the Newton
system through a primal–dual augmented Lagrangian (stabilised SQP; Gill & Robinson 2013): with
penalty ρ = 1/δ the step solves

    [ W + Σ + δ_w I   Jᵀ  ] [ dx ]     [ ∇f + Jᵀλ − barrier gradient ]
    [ J             −δ I  ] [ dλ ] = − [ c                            ]

for the current multipliers λ, so the KKT matrix condenses exactly to the positive-definite
matrix W + Σ + δ_w I + ρ JᵀJ (the slacks are eliminated row by row). Its inertia is correct
exactly when its block Cholesky succeeds, which makes the factorisation the inertia test;
δ_w grows until it does. W is the exact Hessian of the Lagrangian (cost Hessian plus the
constraints' curvature at λ). Every linear system is bordered block-tridiagonal and solved by
``linalg`` (block Cholesky in a ``lax.while_loop``, Schur complement for the globals); each step is then
refined towards the exact (δ = 0) KKT system, with the regularised factor as preconditioner.
When the full step increases the infeasibility, IPOPT's second-order corrections are tried;
when the line search rejects every trial, IPOPT's soft restoration (a step that reduces the
barrier problem's primal–dual error) and its filter reset; and when steps keep being rejected
with the violation above tolerance, a restoration phase (IPOPT's, with a least-squares infeasibility measure:
damped Gauss–Newton steps on ½‖c‖² within the bounds' barrier) until a point acceptable to the
filter is found.

Rows and the cost are scaled at the starting point as IPOPT's gradient-based scaling does
(no row or cost gradient above 100). The whole solve is one ``lax.while_loop``: it can be
jitted and vmapped; a non-finite value stops it with status ``NAN`` and the last finite iterate.
"""

import dataclasses
import enum
from typing import Callable

import jax
import jax.numpy as jnp

from jaxmm.solver import linalg, rows
from jaxmm import stagewise

EQUALITIES = ("path_equality", "transition_equality")
INEQUALITIES = ("path_inequality", "transition_inequality")
GROUPS = EQUALITIES + INEQUALITIES


class Status(enum.IntEnum):
    """Why a solve stopped."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    STALLED = 2  # feasible, but no acceptable step improves the objective any more
    NAN = 3  # a non-finite value appeared; the last finite iterate is returned
    RUNNING = 4
    # Infeasible, and the restoration phase found no point the filter accepts: a locally
    # infeasible problem, or a restoration that failed (``Solution.violation`` says how far from
    # feasible it stopped; with the restoration phase turned off, a line search that failed).
    INFEASIBLE = 5
    INTERRUPTED = 6  # stopped by the user (Ctrl-C) between iterations; the last iterate is returned
    TIME_LIMIT = 7  # stopped when its time budget ran out, between iterations; the last iterate is returned

    @property
    def message(self):
        return {
            Status.CONVERGED: "converged: feasibility, stationarity and complementarity within tolerance",
            Status.MAX_ITERATIONS: "stopped at the iteration limit before converging",
            Status.STALLED: "stalled: feasible, but no acceptable step improves the objective",
            Status.NAN: "a non-finite value appeared; returned the last finite iterate",
            Status.RUNNING: "running",
            Status.INFEASIBLE: "infeasible: the restoration phase found no acceptable point with the constraint "
                               "violation above tolerance (locally infeasible, or the restoration failed; see the "
                               "violation)",
            Status.INTERRUPTED: "interrupted before converging; returned the last iterate",
            Status.TIME_LIMIT: "stopped when the time budget ran out, before converging; returned the last iterate",
        }[self]


SLACK_STARTS = ("pushed", "guess")


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings (static).

    tolerance: max constraint violation (the NLP's own units: |c|, distance of g to [l, u]);
    100× tighter than the paper's IPOPT ``constr_viol_tol``; stationarity: scaled dual
    infeasibility and complementarity (IPOPT's E₀ without the violation), the paper's IPOPT
    ``tol``; max_iterations: Newton iterations; barrier0: the first barrier parameter μ;
    barrier_factor, barrier_power: μ ← min(factor μ, μ^power) once the barrier problem is
    solved to barrier_tolerance_factor × μ, but not below barrier_min / 10 nor below
    stationarity / (barrier_tolerance_factor + 1) (IPOPT's floor: a barrier problem solved
    there meets the stationarity tolerance already); dual_regularisation: δ = 1/ρ of the
    equality rows; regularisation_decrease: the inertia correction's first δ_w > 0 is the last
    one needed times this (IPOPT's κ_w⁻ is 1/3), growing ×8 from there until the Newton matrix
    factors; line_search_steps: backtracking halvings; max_gradient: scaling target;
    max_rejections: consecutive rejected steps before the restoration phase (violation above
    tolerance) or ``STALLED``; max_short_steps, short_step: the restoration phase also starts
    after max_short_steps iterations in a row whose steps (rejected ones included) were shorter
    than short_step and that together cut the violation by less than 10 % (0 turns this
    off): a locally infeasible problem's Newton steps run into the bounds and are cut to
    ≈ 1e-4, which the line search accepts for 1000 iterations or more; max_filter_resets: how
    often, per barrier parameter, a step that only the filter rejected empties the filter
    (IPOPT's filter reset heuristic); max_soft_steps: how many
    consecutive iterations may take a soft-restoration step (IPOPT's: when the line search
    rejects every trial, the step to the fraction-to-boundary length is taken if it cuts the
    primal–dual error of the barrier problem by 0.9999; 0 turns it off);
    max_restoration_iterations: iterations of one restoration phase before ``INFEASIBLE`` (0
    turns the phase off: then ``max_rejections`` rejected steps far from feasible end the solve
    ``INFEASIBLE``); slack_start: where the inequality rows' slacks start: ``"pushed"`` (IPOPT's
    rule, the default) at the rows' values at the starting point pushed inside its bounds,
    ``"guess"`` at their values at the guess as given (with it the published walk-to-fly does
    not converge; docs/design-decisions.md, "The slack start"); ipopt_slacks: δ_w regularises the slacks as it
    does (Z, θ) (IPOPT's δ_s = δ_w; off: (Z, θ) only): with the pushed start, the slacks treated
    as IPOPT treats them, whose steps ours then follow (tools/follow_ipopt.py);
    take-off-and-landing converges in fewer iterations with it, take-off lands on an optimum
    that fails ``validate`` (docs/design-decisions.md);
    progress: called on the host after every iteration as progress(iteration, record) with
    record the history row (``HISTORY_COLUMNS``); None (default) stays silent.
    """

    tolerance: float = 1e-6
    stationarity: float = 1e-4
    max_iterations: int = 3000
    barrier0: float = 0.1
    barrier_min: float = 1e-11
    barrier_factor: float = 0.2
    barrier_power: float = 1.5
    barrier_tolerance_factor: float = 10.0
    dual_regularisation: float = 1e-8
    regularisation_decrease: float = 1e-3
    line_search_steps: int = 30
    max_gradient: float = 100.0
    max_rejections: int = 15
    max_short_steps: int = 15
    short_step: float = 1e-3
    max_filter_resets: int = 5
    max_soft_steps: int = 10
    bound_push: float = 1e-2
    max_restoration_iterations: int = 100
    slack_start: str = "pushed"
    ipopt_slacks: bool = False
    progress: Callable | None = None

    def __post_init__(self):
        if self.slack_start not in SLACK_STARTS:
            raise ValueError(f"Options.slack_start must be one of {SLACK_STARTS}, got {self.slack_start!r}")
        if not 0 < self.regularisation_decrease <= 1:
            raise ValueError(f"Options.regularisation_decrease must be in (0, 1], got {self.regularisation_decrease!r}")
        if not 0 < self.short_step <= 1:
            raise ValueError(f"Options.short_step must be in (0, 1], got {self.short_step!r}")
        if self.max_short_steps < 0:
            raise ValueError(f"Options.max_short_steps must be ≥ 0 (0 turns the rule off), got {self.max_short_steps!r}")


def iteration_options(options):
    """``options`` with the settings only ``start`` reads (barrier0, bound_push, max_gradient,
    slack_start) at their defaults. ``advance`` gives the same result with either (tested), so
    one compiled ``advance`` (options are static) serves every start that differs only there: a
    warm start's barrier settings, say."""
    return dataclasses.replace(options, barrier0=Options.barrier0, bound_push=Options.bound_push,
                               max_gradient=Options.max_gradient, slack_start=Options.slack_start)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Multipliers:
    """Multipliers of every constraint group (same shapes as the residuals), in the NLP's units:
    the Lagrangian is f + Σ λ·c (inequalities: λ > 0 at an active upper bound, < 0 at a lower)."""

    path_equality: jax.Array
    transition_equality: jax.Array
    path_inequality: jax.Array
    transition_inequality: jax.Array


HISTORY_COLUMNS = ("objective", "violation", "stationarity", "barrier", "step_length", "regularisation", "linear_solves",
                   "restoration", "factorisations")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Solution:
    """Result of a solve: the optimum (scaled NLP variables), multipliers, why it stopped and
    statistics. ``status`` is a ``Status`` code; ``history`` (max_iterations, 9) has one row per
    iteration with the columns of ``HISTORY_COLUMNS`` (step length 0: step rejected; linear
    solves: block solves with the factor, refinements and second-order corrections included;
    restoration: 1 in an iteration of the restoration phase, whose regularisation is its damping ζ,
    0 otherwise; factorisations: the inertia correction's work, the diagonal blocks factored over
    all its attempts divided by the number of blocks: 1 when the first attempt worked, more for
    each that failed, a failed one counting the blocks it factored and the indefinite one);
    rows past ``iterations`` are NaN. ``barrier_updates`` counts the decreases of μ (outer iterations).
    ``bound_multipliers`` (lower, upper), each a tuple over (Z, θ, path slacks, transition
    slacks) in the solver's scaling, are for warm starts. ``slacks`` (path, transition): the
    inequality rows' slacks, scaled by the row factors; ``scaling`` = (cost factor (), per-row
    factors of the four groups): the solver minimised cost factor × f subject to row factor ×
    c. Both let ``sensitivity`` rebuild the barrier terms in the NLP's units."""

    Z: jax.Array
    theta: jax.Array
    multipliers: Multipliers
    status: jax.Array
    objective: jax.Array
    violation: jax.Array
    violation_per_group: dict
    stationarity: jax.Array
    iterations: jax.Array
    barrier_updates: jax.Array
    history: jax.Array
    bound_multipliers: tuple
    slacks: tuple
    scaling: tuple


def violation(nlp, Z, theta, r=None):
    """Max constraint violation over every group (the NLP's units) and per group; ``r``: the
    residuals at (Z, θ) when they are at hand."""
    r = stagewise.residuals(nlp, Z, theta) if r is None else r
    groups = dict(
        path_equality=jnp.abs(r.path_equality),
        transition_equality=jnp.abs(r.transition_equality),
        path_inequality=outside(r.path_inequality, nlp.path_lower, nlp.path_upper),
        transition_inequality=outside(r.transition_inequality, nlp.transition_lower, nlp.transition_upper),
        z_box=outside(Z, nlp.z_lower, nlp.z_upper),
        theta_box=outside(theta, nlp.theta_lower, nlp.theta_upper),
    )
    per_group = {k: jnp.max(v, initial=0.0) for k, v in groups.items()}
    return jnp.max(jnp.stack(list(per_group.values()))), per_group


def outside(value, lower, upper):
    """Distance of value to [lower, upper] (0 inside)."""
    return jnp.maximum(jnp.maximum(lower - value, value - upper), 0.0)


def _row_scale(r, max_gradient):
    """IPOPT's gradient-based row scaling: min(1, max_gradient / ‖∇cᵢ‖∞) per row."""
    largest = jnp.maximum(jnp.max(jnp.abs(r.jz), axis=-1, initial=0.0), jnp.max(jnp.abs(r.jt), axis=-1, initial=0.0))
    if r.jn is not None:
        largest = jnp.maximum(largest, jnp.max(jnp.abs(r.jn), axis=-1, initial=0.0))
    return jnp.minimum(1.0, max_gradient / jnp.maximum(largest, 1e-300))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Bounds:
    """Bounds of the primal leaves (Z, θ, path slacks, transition slacks) and their masks."""

    lower: tuple
    upper: tuple
    has_lower: tuple  # finite lower bound on a non-fixed entry
    has_upper: tuple
    free: tuple  # not fixed (lower < upper)


def _bounds(nlp, slack_scale):
    """``_Bounds`` of (Z, θ, path slacks, transition slacks); a slack is in the row's scaled units."""
    lower = (nlp.z_lower, nlp.theta_lower, nlp.path_lower * slack_scale[0], nlp.transition_lower * slack_scale[1])
    upper = (nlp.z_upper, nlp.theta_upper, nlp.path_upper * slack_scale[0], nlp.transition_upper * slack_scale[1])
    free = tuple(lo < hi for lo, hi in zip(lower, upper))
    has_lower = tuple(jnp.isfinite(lo) & f for lo, f in zip(lower, free))
    has_upper = tuple(jnp.isfinite(hi) & f for hi, f in zip(upper, free))
    return _Bounds(lower, upper, has_lower, has_upper, free)


def _distances(P, bounds):
    """Distances to the finite bounds (1 where there is none)."""
    dl = tuple(jnp.where(m, p - lo, 1.0) for p, lo, m in zip(P, bounds.lower, bounds.has_lower))
    du = tuple(jnp.where(m, hi - p, 1.0) for p, hi, m in zip(P, bounds.upper, bounds.has_upper))
    return dl, du


def _barrier(P, bounds, mu):
    dl, du = _distances(P, bounds)
    return -mu * sum(
        jnp.sum(jnp.where(ml, jnp.log(a), 0.0)) + jnp.sum(jnp.where(mu_, jnp.log(b), 0.0))
        for a, b, ml, mu_ in zip(dl, du, bounds.has_lower, bounds.has_upper)
    )


def _tmap(fn, *trees):
    return tuple(fn(*leaves) for leaves in zip(*trees))


def _dot(a, b):
    return sum(jnp.sum(x * y) for x, y in zip(a, b))


def _max_abs(tree):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(leaf), initial=0.0) for leaf in tree]))


def _interior(P, bounds, kappa=1e-2):
    """Move P strictly inside its bounds (IPOPT's bound push)."""

    def push(p, lo, hi, ml, mu_, free):
        width = jnp.where(ml & mu_, hi - lo, jnp.inf)
        pl = jnp.minimum(kappa * jnp.maximum(1.0, jnp.abs(jnp.where(ml, lo, 0.0))), kappa * width)
        pu = jnp.minimum(kappa * jnp.maximum(1.0, jnp.abs(jnp.where(mu_, hi, 0.0))), kappa * width)
        p = jnp.where(ml, jnp.maximum(p, lo + pl), p)
        p = jnp.where(mu_, jnp.minimum(p, hi - pu), p)
        return jnp.where(free, p, lo)

    return _tmap(push, P, bounds.lower, bounds.upper, bounds.has_lower, bounds.has_upper, bounds.free)


def _fraction_to_boundary(values, steps, tau):
    """Largest α ≤ 1 keeping every value (distance or multiplier) ≥ (1 − τ) of itself."""
    alpha = jnp.asarray(1.0)
    for v, d in zip(values, steps):
        ratio = jnp.where(d < 0, -tau * v / jnp.where(d < 0, d, -1.0), jnp.inf)
        alpha = jnp.minimum(alpha, jnp.min(ratio, initial=jnp.inf))
    return alpha


def _condensed_solve(chol, J, weights, inv_sigma, free, K, ax, a_s, a_c):
    """The regularised KKT system [H + Σ, Jᵀ; J, −diag(1/weights)] with right-hand sides ax
    (dual rows of (Z, θ)), a_s (dual rows of the slacks) and a_c (constraint rows), by condensing
    onto ``chol``, the block-tridiagonal factor of H + Σ + Jᵀ diag(weights) J (slacks eliminated
    row by row with ``inv_sigma`` = 1/(their diagonal)): returns (dx, ds, dy). ``free``: masks
    (0 where fixed) of Z and θ."""
    fz, ft = free
    shifts = a_c[:2] + tuple(ag + a * i for ag, a, i in zip(a_c[2:], a_s, inv_sigma))
    rz, rt = ax
    for r, w, sh in zip(J, weights, shifts):
        pz, pt = rows.pull(r, w * sh, K)
        rz, rt = rz + pz, rt + pt
    dz, dt = linalg.solve(chol, rz * fz, rt * ft)
    dz, dt = dz * fz, dt * ft
    dy = tuple(w * (rows.apply(r, dz, dt) - sh) for r, w, sh in zip(J, weights, shifts))
    ds = tuple((a + dv) * i for a, dv, i in zip(a_s, dy[2:], inv_sigma))
    return (dz, dt), ds, dy


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """The solver between two iterations (``start``, ``advance``, ``finish``): the primal–dual
    iterate in the solver's scaling, the barrier parameter, the filter, the counters and the
    constants fixed at the start (scaling, filter envelope)."""

    P: tuple  # (Z, θ, path slacks, transition slacks)
    y: tuple  # scaled multipliers of (path eq, transition eq, path ineq, transition ineq)
    zl: tuple  # bound multipliers per primal leaf
    zu: tuple
    mu: jax.Array
    regularisation: jax.Array  # last nonzero δ_w that was needed (0: none yet)
    forced: jax.Array  # δ_w to start from after a rejected step (0 after an accepted one)
    filter_theta: jax.Array
    filter_phi: jax.Array
    filter_count: jax.Array
    filter_resets: jax.Array  # filter resets since the barrier parameter last changed
    soft_steps: jax.Array  # consecutive soft-restoration steps (0: the line search accepted the last step)
    rejections: jax.Array
    short_steps: jax.Array  # consecutive iterations with steps below short_step and < 10 % less violation
    short_violation: jax.Array  # the violation where those iterations began
    iterations: jax.Array
    barrier_updates: jax.Array
    status: jax.Array
    violation: jax.Array
    stationarity: jax.Array
    history: jax.Array
    scaling: tuple  # (cost factor, per-row factors of the four groups)
    theta_max: jax.Array  # the filter's envelope on the infeasibility, from the starting point
    theta_min: jax.Array  # infeasibility below which Armijo steps on the barrier function may be taken
    restoring: jax.Array  # in the restoration phase
    restoration_theta: jax.Array  # infeasibility where the restoration phase started
    restoration_iterations: jax.Array  # iterations of the current restoration phase


FILTER_SIZE = 128
REFINEMENT_STEPS = 10  # most refinements of a step towards the exact KKT system (while the residual falls)
# Refinement ends once the exact KKT residual is below this fraction of the right-hand side (or
# stops falling by 10 %). A tighter 1e-14 costs 8–10 solves per iteration on take-off for no
# fewer iterations (docs/design-decisions.md, "Iterative refinement to 1e-10").
REFINEMENT_RATIO = 1e-10
# The restoration phase minimises ½‖c‖² + (μ / RESTORATION_PENALTY) × barrier: IPOPT's weighs its
# ℓ1 infeasibility by ρ = 1000 against the barrier and its proximal term. (With μ itself, the
# barrier held walk-to-fly N = 20 at a violation of 0.5.)
RESTORATION_PENALTY = 1000.0
SOC_STEPS = 4  # second-order corrections per iteration (IPOPT's max_soc)


def _scaling(nlp, Z0, theta0, options):
    """(cost factor, per-row factors of the four groups) at the starting point: IPOPT's
    gradient-based scaling, no row or cost gradient above options.max_gradient."""
    B0 = stagewise.blocks(nlp, Z0, theta0)
    cost_scale = jnp.minimum(1.0, options.max_gradient / jnp.maximum(
        jnp.maximum(jnp.max(jnp.abs(B0.cost_z)), jnp.max(jnp.abs(B0.cost_theta))), 1e-300))
    return cost_scale, tuple(_row_scale(rows.group_rows(B0, g), options.max_gradient) for g in GROUPS)


def _frame(nlp, scaling):
    """What every iteration derives from the scaling: the inequality rows that constrain
    something (``active``, per inequality group), the bounds in the solver's units, and
    ``evaluate(P)`` → (scaled cost, scaled equality residuals (c, g − s), raw residuals)."""
    cost_scale, row_scale = scaling[0], tuple(scaling[1])
    # Inequality rows with no finite bound constrain nothing: their slack follows g.
    active = (
        jnp.broadcast_to(jnp.isfinite(nlp.path_lower) | jnp.isfinite(nlp.path_upper), row_scale[2].shape),
        jnp.broadcast_to(jnp.isfinite(nlp.transition_lower) | jnp.isfinite(nlp.transition_upper), row_scale[3].shape),
    )

    def evaluate(P):
        Z, theta, sp, st = P
        r = stagewise.residuals(nlp, Z, theta)
        c = (
            r.path_equality * row_scale[0],
            r.transition_equality * row_scale[1],
            (r.path_inequality * row_scale[2] - sp) * active[0],
            (r.transition_inequality * row_scale[3] - st) * active[1],
        )
        return cost_scale * r.cost, c, r

    return active, _bounds(nlp, row_scale[2:]), evaluate


def _rounding(dtype):
    """The relative allowance of the line search's comparisons: 10 ε, IPOPT's."""
    return 10 * jnp.finfo(dtype).eps


def in_filter(theta, phi, filter_theta, filter_phi):
    """Whether (θ, φ) is rejected by the filter: worse than an entry in both, by more than 10 ε
    of that entry (IPOPT's comparison), so that no entry rejects the point it was made from."""
    rounding = _rounding(filter_theta.dtype)
    tolerance = rounding * jnp.abs(jnp.where(jnp.isfinite(filter_phi), filter_phi, 0.0))
    return jnp.any((theta - filter_theta > rounding * filter_theta) & (phi - filter_phi > tolerance))


def _infeasibility(c):
    return sum(jnp.sum(jnp.abs(v)) for v in c)


def start(nlp, Z0, theta0, options=Options(), multipliers=None, bound_multipliers=None, scaling=None):
    """The solver's ``State`` before its first iteration from (Z0 (K, nz), θ0 (ng,)), pushed
    inside the bounds; the constraint multipliers warm-started with ``multipliers`` (a
    ``Multipliers``), the bound multipliers with ``bound_multipliers`` (both from a previous
    ``Solution``); ``scaling``: a previous ``Solution.scaling`` to solve in (default: computed
    at the starting point)."""
    dtype = Z0.dtype
    scaling = _scaling(nlp, Z0, theta0, options) if scaling is None else (scaling[0], tuple(scaling[1]))
    cost_scale, row_scale = scaling
    _, bounds, evaluate = _frame(nlp, scaling)
    if options.slack_start == "pushed":  # the rows at the point the solve starts from, as IPOPT's slacks
        Z0, theta0 = _interior((Z0, theta0), bounds, options.bound_push)
    r0 = stagewise.residuals(nlp, Z0, theta0)
    P0 = _interior((Z0, theta0, r0.path_inequality * row_scale[2], r0.transition_inequality * row_scale[3]), bounds,
                   options.bound_push)
    if multipliers is None:
        y0 = tuple(jnp.zeros_like(s) for s in row_scale)
    else:
        y0 = tuple(cost_scale * getattr(multipliers, g) / s for g, s in zip(GROUPS, row_scale))
    ones = tuple(jnp.ones_like(p) for p in P0)
    zl0, zu0 = (ones, ones) if bound_multipliers is None else bound_multipliers
    zl0 = _tmap(lambda o, m: jnp.where(m, o, 0.0), zl0, bounds.has_lower)
    zu0 = _tmap(lambda o, m: jnp.where(m, o, 0.0), zu0, bounds.has_upper)
    _, c0, _ = evaluate(P0)
    envelope = jnp.maximum(1.0, _infeasibility(c0))
    v0, _ = violation(nlp, P0[0], P0[1])
    state = State(
        P=P0, y=y0, zl=zl0, zu=zu0, mu=jnp.asarray(options.barrier0, dtype),
        regularisation=jnp.asarray(0.0, dtype), forced=jnp.asarray(0.0, dtype),
        filter_theta=jnp.full(FILTER_SIZE, jnp.inf, dtype).at[0].set(1e4 * envelope),
        filter_phi=jnp.full(FILTER_SIZE, jnp.inf, dtype).at[0].set(-jnp.inf),
        filter_count=jnp.asarray(1), filter_resets=jnp.asarray(0), soft_steps=jnp.asarray(0),
        rejections=jnp.asarray(0), short_steps=jnp.asarray(0), short_violation=v0, iterations=jnp.asarray(0),
        barrier_updates=jnp.asarray(0), status=jnp.asarray(int(Status.RUNNING)), violation=v0,
        stationarity=jnp.asarray(jnp.inf, dtype),
        history=jnp.full((options.max_iterations, len(HISTORY_COLUMNS)), jnp.nan, dtype),
        scaling=scaling, theta_max=1e4 * envelope, theta_min=1e-4 * envelope,
        restoring=jnp.asarray(False), restoration_theta=jnp.asarray(0.0, dtype),
        restoration_iterations=jnp.asarray(0),
    )
    # No weak types: a cold start (θ0 from Python floats) and a warm one must give the same avals,
    # so that one compiled ``advance`` serves both.
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x)), state)


def advance(nlp, state, options=Options(), until=None):
    """Iterate from ``state`` until the solve stops (converged, infeasible, stalled, NaN) or
    ``state.iterations`` reaches ``until`` (a traced int is fine: one compilation serves every
    count; default and cap: options.max_iterations). Returns the new ``State``.

    ``advance(nlp, advance(nlp, s, o, k), o)`` is ``advance(nlp, s, o)``: a solve can be run in
    slices, with the host deciding between them whether to go on (``solve.solve_task``'s time budget
    and Ctrl-C)."""
    K = state.P[0].shape[0]
    dtype = state.P[0].dtype
    cost_scale, row_scale = state.scaling[0], tuple(state.scaling[1])
    active, bounds, evaluate = _frame(nlp, state.scaling)
    delta_c = options.dual_regularisation
    limit = options.max_iterations if until is None else jnp.minimum(until, options.max_iterations)
    fixed_z = (~bounds.free[0]).astype(dtype)
    fixed_t = (~bounds.free[1]).astype(dtype)
    fz, ft = 1 - fixed_z, 1 - fixed_t
    supports = stagewise.row_supports(nlp)
    coupled = rows.coupled_columns(supports)

    def complementarity(dl, du, zl, zu, mu):
        """distance · z − μ per bound (0 where there is none), lower bounds' leaves first, from
        the distances (dl, du) = ``_distances``."""
        return _tmap(lambda a, z, m: jnp.where(m, a * z - mu, 0.0), dl + du, zl + zu,
                     bounds.has_lower + bounds.has_upper)

    def primal_dual_error(dual, c, comp):
        """The barrier problem's primal–dual error, IPOPT's soft-restoration measure: mean |dual
        infeasibility| + mean |residual| + mean |distance · z − μ|."""
        return sum(sum(jnp.sum(jnp.abs(v)) for v in tree) / max(sum(v.size for v in tree), 1)
                   for tree in (dual, c, comp))

    def primal_dual_error_at(P, y, zl, zu, mu):
        """``primal_dual_error`` at a point the iteration has no Jacobian blocks of (a trial)."""

        def lagrangian(P):
            f, c, _ = evaluate(P)
            return f + _dot(y, c), c

        grad, c = jax.grad(lagrangian, has_aux=True)(P)
        dual = _tmap(lambda g, a, b, f: jnp.where(f, g - a + b, 0.0), grad, zl, zu, bounds.free)
        return primal_dual_error(dual, c, complementarity(*_distances(P, bounds), zl, zu, mu))

    def barrier_terms(dl, du, zl, zu, mu):
        """(Σ, the primal–dual barrier Hessian, and the barrier gradient) per primal leaf, from
        the distances to the bounds (dl, du) and the bound multipliers."""
        sigma = _tmap(lambda a, b, p, q, ml, mu_: jnp.where(ml, p / a, 0.0) + jnp.where(mu_, q / b, 0.0),
                      dl, du, zl, zu, bounds.has_lower, bounds.has_upper)
        bgrad = _tmap(lambda a, b, ml, mu_: jnp.where(ml, -mu / a, 0.0) + jnp.where(mu_, mu / b, 0.0),
                      dl, du, bounds.has_lower, bounds.has_upper)
        return sigma, bgrad

    def bound_steps(dl, du, zl, zu, dP, mu, tau):
        """The bound multipliers' Newton steps (dzl, dzu) for the primal step dP, and the
        fraction-to-boundary lengths (τ) of the primal and of the multiplier steps."""
        dzl = _tmap(lambda a, p, d, m: jnp.where(m, mu / a - p - p * d / a, 0.0), dl, zl, dP, bounds.has_lower)
        dzu = _tmap(lambda b, q, d, m: jnp.where(m, mu / b - q + q * d / b, 0.0), du, zu, dP, bounds.has_upper)
        alpha_max = _fraction_to_boundary(
            dl + du, _tmap(lambda d, m: jnp.where(m, d, 0.0), dP, bounds.has_lower)
            + _tmap(lambda d, m: jnp.where(m, -d, 0.0), dP, bounds.has_upper), tau)
        return dzl, dzu, alpha_max, _fraction_to_boundary(zl + zu, dzl + dzu, tau)

    def jacobian_rows(B):
        """The constraint rows' Jacobian blocks in the solver's units (inequality rows that
        constrain nothing left out)."""
        J = tuple(rows.scaled(rows.group_rows(B, g, supports.get(g)), s) for g, s in zip(GROUPS, row_scale))
        return J[:2] + tuple(rows.scaled(r, a) for r, a in zip(J[2:], active))

    def attempted(chol):
        """Diagonal blocks a factorisation attempt factored, the indefinite one included."""
        return jnp.minimum(chol.factored + 1, K)

    def restoration(state, B):
        """One iteration of the restoration phase: a primal–dual step on ½‖c‖² + μ_R × barrier
        (μ_R = μ min(1, ‖c‖∞) / RESTORATION_PENALTY, the cost left out) with the Gauss–Newton
        Hessian JᵀJ, damped by ζ D² (ζ = √(μ / RESTORATION_PENALTY), D = min(1, 1/|P|), IPOPT's
        proximal weights), and a
        backtracking Armijo search. The phase ends, as IPOPT's, at a point that the filter
        (which holds the point the phase started from) accepts and whose infeasibility ‖c‖₁
        is at most 0.9 of that point's; it fails (status ``INFEASIBLE``) when no step
        decreases its measure (a locally infeasible point) or after
        ``max_restoration_iterations``. Back in the barrier problem the constraint multipliers
        start from 0 (IPOPT's default) and the bound multipliers on its central path (μ / distance)."""
        P, zl, zu = state.P, state.zl, state.zu
        now = evaluate(P)
        c = now[1]
        # The barrier's weight shrinks with the infeasibility, as the gradient of ½‖c‖² does
        # (IPOPT's ℓ1 measure keeps its gradient): entered at a violation of 2e-6, a fixed
        # μ / 1000 let the barrier push walk-to-fly's active bounds apart, the violation up to
        # 1e-3 and the objective from 6.2e7 to 1.8e9 in 100 iterations.
        mu = state.mu / RESTORATION_PENALTY * jnp.minimum(1.0, _max_abs(c))
        J = jacobian_rows(B)
        dl, du = _distances(P, bounds)
        zeta = jnp.sqrt(state.mu / RESTORATION_PENALTY)
        D2 = _tmap(lambda r, f: jnp.where(f, jnp.minimum(1.0, 1.0 / jnp.maximum(jnp.abs(r), 1e-300)) ** 2, 0.0),
                   P, bounds.free)
        sigma, bgrad = barrier_terms(dl, du, zl, zu, mu)
        rx = _tmap(lambda b, f: jnp.where(f, b, 0.0), bgrad, bounds.free)
        inv_sigma = tuple(jnp.where(s > 0, 1.0 / jnp.where(s > 0, s + zeta * d, 1.0), 0.0) for s, d in zip(sigma[2:], D2[2:]))
        # The rows enter with weight 1: [H Jᵀ; J −I] is the Gauss–Newton system of ½‖c‖².
        weights = (jnp.ones_like(c[0]), jnp.ones_like(c[1])) + tuple(
            jnp.where(a, 1.0 / (i + 1.0), 0.0) for i, a in zip(inv_sigma, active))
        D, L, Bd, C = rows.grams(J, weights, K)
        D = fz[:, :, None] * (D + jax.vmap(jnp.diag)(sigma[0] + zeta * D2[0])) * fz[:, None, :] + jax.vmap(jnp.diag)(fixed_z)
        C = ft[:, None] * (C + jnp.diag(sigma[1] + zeta * D2[1])) * ft[None, :] + jnp.diag(fixed_t)
        chol = linalg.factor(D, fz[1:, :, None] * L * fz[:-1, None, :], fz[:, :, None] * Bd * ft[None, None, :], C,
                             coupled=coupled)
        dx, ds, _ = _condensed_solve(chol, J, weights, inv_sigma, (fz, ft), K,
                                     (-rx[0], -rx[1]), (-rx[2], -rx[3]), tuple(-v for v in c))
        dP = dx + ds
        tau = jnp.maximum(0.99, 1.0 - mu)
        dzl, dzu, alpha_max, alpha_z = bound_steps(dl, du, zl, zu, dP, mu, tau)

        def merit(Pt, ct):
            return 0.5 * sum(jnp.sum(v * v) for v in ct) + _barrier(Pt, bounds, mu)

        def trial(alpha):
            """(the measure, the cost, the scaled and the raw residuals) at the step α."""
            Pt = _tmap(lambda p, d: p + alpha * d, P, dP)
            f, ct, rt = evaluate(Pt)
            return merit(Pt, ct), f, ct, rt

        psi0 = merit(P, c)
        linear = tuple(rows.apply(r, *dx) for r in J)
        linear = linear[:2] + tuple(jnp.where(a, v - d, 0.0) for v, d, a in zip(linear[2:], ds, active))
        slope = _dot(c, linear) + _dot(bgrad, dP)

        def sufficient(alpha, psi):
            return psi - psi0 - 1e-4 * alpha * slope <= _rounding(dtype) * jnp.abs(psi0)

        def shorter(carry):
            alpha, _, count = carry
            return 0.5 * alpha, trial(0.5 * alpha), count + 1

        def searching(carry):
            # ``state.restoring``: under vmap both branches run, and instances outside the phase
            # must not keep the search going.
            alpha, (psi, _, _, _), count = carry
            return state.restoring & ~sufficient(alpha, psi) & (count < options.line_search_steps)

        alpha, (psi, f_new, c_new, r_new), _ = jax.lax.while_loop(
            searching, shorter, (alpha_max, trial(alpha_max), jnp.asarray(0)))
        found = chol.ok & (slope < 0) & jnp.isfinite(psi) & sufficient(alpha, psi)
        step = jnp.where(found, alpha, 0.0)
        step_z = jnp.where(found, alpha_z, 0.0)
        P_new = _tmap(lambda p, d: p + step * d, P, dP)
        # Without a step the point stays and so do its residuals (``trial``'s are at the last α).
        f_new, c_new, r_new = jax.tree.map(lambda a, b: jnp.where(found, a, b), (f_new, c_new, r_new), now)
        dl_new, du_new = _distances(P_new, bounds)
        zl_new = _tmap(lambda z, d, a, m: jnp.where(m, jnp.clip(z + step_z * d, mu / (1e10 * a), 1e10 * mu / a), 0.0),
                       zl, dzl, dl_new, bounds.has_lower)
        zu_new = _tmap(lambda z, d, b, m: jnp.where(m, jnp.clip(z + step_z * d, mu / (1e10 * b), 1e10 * mu / b), 0.0),
                       zu, dzu, du_new, bounds.has_upper)
        theta_new = _infeasibility(c_new)
        phi_new = f_new + _barrier(P_new, bounds, state.mu)
        done = found & (theta_new <= 0.9 * state.restoration_theta) & ~in_filter(
            theta_new, phi_new, state.filter_theta, state.filter_phi)
        count = state.restoration_iterations + 1
        failed = ~done & (~found | (count >= options.max_restoration_iterations))
        v_new, _ = violation(nlp, P_new[0], P_new[1], r_new)
        status = jnp.where(failed, int(Status.INFEASIBLE), int(Status.RUNNING))
        # Back in the barrier problem, the bound multipliers start on its central path.
        zl_new = _tmap(lambda z, a, m: jnp.where(done & m, state.mu / a, z), zl_new, dl_new, bounds.has_lower)
        zu_new = _tmap(lambda z, b, m: jnp.where(done & m, state.mu / b, z), zu_new, du_new, bounds.has_upper)
        record = jnp.stack([r_new.cost, v_new, state.stationarity, state.mu, step, zeta, 1.0, 1.0,
                            attempted(chol).astype(dtype) / K])
        if options.progress is not None:
            jax.debug.callback(options.progress, state.iterations, record)
        return dataclasses.replace(
            state, P=P_new, zl=zl_new, zu=zu_new,
            y=jax.tree.map(lambda v: jnp.where(done, 0.0, v), state.y),
            restoring=~done, restoration_iterations=count, status=status, violation=v_new,
            # The regularisation escalated by the rejected steps before the phase is forgotten.
            soft_steps=jnp.asarray(0), rejections=jnp.asarray(0), short_steps=jnp.asarray(0),
            forced=jnp.zeros_like(state.forced),
            regularisation=jnp.zeros_like(state.regularisation),
            history=state.history.at[state.iterations].set(record), iterations=state.iterations + 1,
        )

    def body(state):
        # The path multipliers let the blocks carry the path Hessian's kinematic curvature,
        # computed with their Jacobian (``newton``'s curvature uses the same multipliers).
        B = stagewise.blocks(nlp, state.P[0], state.P[1], path_multipliers=(state.y[0] * row_scale[0], state.y[2] * row_scale[2]))
        if options.max_restoration_iterations == 0:
            return newton(state, B)
        return jax.lax.cond(state.restoring, restoration, newton, state, B)

    def newton(state, B):
        P, y, zl, zu = state.P, state.y, state.zl, state.zu
        Z, theta = P[0], P[1]
        _, c, r_now = evaluate(P)
        J = jacobian_rows(B)
        # Gradient of the Lagrangian f + yᵀc (bounds apart), per primal leaf.
        gz, gt = cost_scale * B.cost_z, cost_scale * B.cost_theta
        for r, yi in zip(J, y):
            pz, pt = rows.pull(r, yi, K)
            gz, gt = gz + pz, gt + pt
        grad = (gz, gt, -y[2], -y[3])
        dual = _tmap(lambda g, a, b, f: jnp.where(f, g - a + b, 0.0), grad, zl, zu, bounds.free)
        dl, du = _distances(P, bounds)
        n_mult = sum(v.size for v in y) + sum(v.size for v in zl) + sum(v.size for v in zu)
        n_var = sum(p.size for p in P)
        s_d = jnp.maximum(100.0, (sum(jnp.sum(jnp.abs(v)) for v in y + zl + zu)) / max(n_mult, 1)) / 100.0
        s_c = jnp.maximum(100.0, (sum(jnp.sum(jnp.abs(v)) for v in zl + zu)) / max(2 * n_var, 1)) / 100.0
        dual_error = _max_abs(dual) / s_d
        primal_error = _max_abs(c)

        def complementarity_error(mu):
            return _max_abs(complementarity(dl, du, zl, zu, mu)) / s_c

        v_now = state.violation
        error0 = jnp.maximum(dual_error, complementarity_error(0.0))
        converged = (error0 <= options.stationarity) & (v_now <= options.tolerance)
        # Short steps that no longer cut the violation: restoration from here, without a step.
        crawling = ((options.max_short_steps > 0) & (options.max_restoration_iterations > 0)
                    & (state.short_steps >= options.max_short_steps) & (v_now > options.tolerance) & ~converged)

        # Barrier update (monotone, IPOPT): as long as the barrier problem is solved to κ_ε μ.
        floor = max(options.barrier_min / 10, options.stationarity / (options.barrier_tolerance_factor + 1))

        def solved(carry):
            mu, _ = carry
            return (jnp.maximum(jnp.maximum(dual_error, primal_error), complementarity_error(mu))
                    <= options.barrier_tolerance_factor * mu) & (mu > floor)

        def decrease(carry):
            mu, count = carry
            new = jnp.maximum(floor, jnp.minimum(options.barrier_factor * mu, mu**options.barrier_power))
            return new, count + 1

        mu, updates = jax.lax.while_loop(solved, decrease, (state.mu, jnp.asarray(0)))
        reset = updates > 0
        filter_theta = jnp.where(reset, jnp.full_like(state.filter_theta, jnp.inf).at[0].set(state.theta_max), state.filter_theta)
        filter_phi = jnp.where(reset, jnp.full_like(state.filter_phi, jnp.inf).at[0].set(-jnp.inf), state.filter_phi)
        filter_count = jnp.where(reset, 1, state.filter_count)
        filter_resets = jnp.where(reset, 0, state.filter_resets)
        soft_steps = jnp.where(reset, 0, state.soft_steps)
        tau = jnp.maximum(0.99, 1.0 - mu)

        sigma, bgrad = barrier_terms(dl, du, zl, zu, mu)
        rx = _tmap(lambda g, b: g + b, grad, bgrad)  # the barrier problem's dual residual
        # Slacks eliminated row by row: dv = d_g (J dx + c_g + r_s / σ_s), ds = (dv − r_s) / σ_s.
        # Fixed slacks (equal bounds) and rows without bounds have σ = 0: their 1/σ is 0.
        # With ``ipopt_slacks`` δ_w regularises the slacks too (IPOPT's δ_s = δ_w): their 1/σ, and
        # so the inequality rows' weights in the condensed matrix, depend on δ_w.
        def slack_terms(delta):
            """(1/(σ_s + δ) per slack, every row's weight in the condensed matrix)."""
            inv = tuple(jnp.where(s > 0, 1.0 / jnp.where(s > 0, s + delta, 1.0), 0.0) for s in sigma[2:])
            weight_g = tuple(jnp.where(a, 1.0 / (i + delta_c), 0.0) for i, a in zip(inv, active))
            return inv, (jnp.full_like(c[0], 1.0 / delta_c), jnp.full_like(c[1], 1.0 / delta_c)) + weight_g

        lagrangian = rows.add(
            tuple(cost_scale * b for b in (B.cost_zz, jnp.zeros_like(B.cost_zz[1:]), B.cost_ztheta, B.cost_thetatheta)),
            stagewise.constraint_curvature(nlp, Z, theta, *(yi * s for yi, s in zip(y, row_scale)),
                                           path_linearisation=B.path_linearisation),
        )
        # The Gram products added into the Lagrangian's blocks: separate (K, n, n) arrays, summed
        # after, cost a pass over the blocks each.
        if options.ipopt_slacks:
            equalities = rows.grams(J[:2], slack_terms(0.0)[1][:2], K, into=lagrangian)

            def condensed(delta):
                return rows.grams(J[2:], slack_terms(delta)[1][2:], K, into=equalities)
        else:
            everything = rows.grams(J, slack_terms(0.0)[1], K, into=lagrangian)

            def condensed(delta):
                return everything

        def fixed_out(hessian):
            """The Newton matrix with the fixed variables' rows and columns out (1 on their
            diagonal), without Σ + δ_w: ``linalg.factor`` adds those block by block, so an
            inertia correction's attempts share one pass over the blocks."""
            D, L, Bd, C = hessian
            return (fz[:, :, None] * D * fz[:, None, :] + jax.vmap(jnp.diag)(fixed_z), fz[1:, :, None] * L * fz[:-1, None, :],
                    fz[:, :, None] * Bd * ft[None, None, :], ft[:, None] * C * ft[None, :] + jnp.diag(fixed_t))

        if not options.ipopt_slacks:
            unshifted = fixed_out(everything)

        # Inertia correction (IPOPT's rule but for the decrease): δ_w = 0 first, then from the last
        # δ_w × regularisation_decrease, ×8. IPOPT's third of the last δ_w kept take-off's δ_w at
        # 1.4–4100× the least that factors (median 5×; the need swings by 1000× between
        # iterations): 702 iterations against 243 with 1e-3 (docs/design-decisions.md, κ_w⁻).
        # Skipping δ_w = 0 saves a factorisation but keeps the steps damped.
        def attempt(delta):
            blocks = fixed_out(condensed(delta)) if options.ipopt_slacks else unshifted
            chol = linalg.factor(*blocks, coupled=coupled, shift=fz * (sigma[0] + delta),
                                 corner_shift=ft * (sigma[1] + delta))
            return chol, chol.ok

        chol0, ok0 = attempt(state.forced)

        def needs_more(carry):
            delta, _, ok, _ = carry
            return (~ok) & (delta < 1e40)

        def grow(carry):
            delta, _, _, work = carry
            resumed = jnp.maximum(1e-20, state.regularisation * options.regularisation_decrease)
            delta = jnp.where(delta == 0.0, jnp.where(state.regularisation == 0.0, 1e-4, resumed),
                              delta * jnp.where(state.regularisation == 0.0, 100.0, 8.0))
            chol, ok = attempt(delta)
            return delta, chol, ok, work + attempted(chol)

        delta_w, chol, factored, work = jax.lax.while_loop(needs_more, grow, (state.forced, chol0, ok0, attempted(chol0)))
        factorisations = work.astype(dtype) / K
        delta_s = delta_w if options.ipopt_slacks else 0.0
        inv_sigma, weights = slack_terms(delta_s)

        def regularised_times(dz, dt):
            """``fixed_out(lagrangian)`` with Σ + δ_w on the free variables' diagonal, times (dz,
            dt), the masks and the diagonal applied to the vectors (no copy of the blocks)."""
            hz, ht = linalg.matvec(*lagrangian, dz * fz, dt * ft)
            return (hz * fz + (fixed_z + fz * (sigma[0] + delta_w)) * dz,
                    ht * ft + (fixed_t + ft * (sigma[1] + delta_w)) * dt)

        def kkt_solve(ax, a_s, a_c):
            return _condensed_solve(chol, J, weights, inv_sigma, (fz, ft), K, ax, a_s, a_c)

        def kkt_residual(ax, a_s, a_c, dx, ds, dy):
            """Residual of the exact KKT system (δ_c = 0) at the step (dx, ds, dy)."""
            hz, ht = regularised_times(*dx)
            for r, dv in zip(J, dy):
                pz, pt = rows.pull(r, dv, K)
                hz, ht = hz + pz, ht + pt
            Jdx = tuple(rows.apply(r, *dx) for r in J)
            return (
                ((ax[0] - hz) * fz, (ax[1] - ht) * ft),
                tuple(jnp.where(i > 0, a - ((sg + delta_s) * d - dv), 0.0)
                      for a, sg, d, dv, i in zip(a_s, sigma[2:], ds, dy[2:], inv_sigma)),
                tuple(a - jd for a, jd in zip(a_c[:2], Jdx[:2]))
                + tuple(jnp.where(act, a - (jd - d), 0.0) for a, jd, d, act in zip(a_c[2:], Jdx[2:], ds, active)),
            )

        def direction(cq):
            """Newton step (primal, multipliers, bound multipliers, their fraction-to-boundary
            lengths) for the scaled equality residuals cq: the iterate's own, or a second-order
            correction's. The regularised solve is refined towards the exact KKT system
            (δ_c = 0): ρ JᵀJ makes the condensed matrix ill-conditioned, and δ_c alone biases
            the step enough to make the last iterations converge only linearly."""
            a = ((-rx[0], -rx[1]), (-rx[2], -rx[3]), tuple(-v for v in cq))
            floor = REFINEMENT_RATIO * jnp.maximum(1.0, _max_abs(jax.tree.leaves(a)))

            def improving(carry):
                k, _, _, size, previous = carry
                return (k < REFINEMENT_STEPS) & (size > floor) & (size < 0.9 * previous)

            def refine(carry):
                k, step, residual, size, _ = carry
                step = jax.tree.map(jnp.add, step, kkt_solve(*residual))
                residual = kkt_residual(*a, *step)
                return k + 1, step, residual, _max_abs(jax.tree.leaves(residual)), size

            step = kkt_solve(*a)
            residual = kkt_residual(*a, *step)
            refinements, (dx, ds, dy), _, _, _ = jax.lax.while_loop(
                improving, refine, (0, step, residual, _max_abs(jax.tree.leaves(residual)), jnp.asarray(jnp.inf, dtype)))
            dP = dx + ds
            dzl, dzu, alpha_max, alpha_z = bound_steps(dl, du, zl, zu, dP, mu, tau)
            return (dP, dy, dzl, dzu), alpha_max, alpha_z, 1 + refinements

        newton, alpha_max, alpha_z, solves = direction(c)
        dP = newton[0]

        # Filter line search on (θ, φ) = (‖c‖₁, f + barrier), IPOPT's acceptance rules.
        cost_now = r_now.cost
        phi0 = cost_scale * cost_now + _barrier(P, bounds, mu)
        theta0_ = _infeasibility(c)
        slope = _dot((cost_scale * B.cost_z, cost_scale * B.cost_theta), dP[:2]) + _dot(bgrad, dP)

        def trial(alpha, dP):
            Pt = _tmap(lambda p, d: p + alpha * d, P, dP)
            f, ct, _ = evaluate(Pt)
            return _infeasibility(ct), f + _barrier(Pt, bounds, mu), ct

        def acceptable(alpha, th, ph):
            """(accepted, an Armijo step, rejected by the filter alone). Comparisons allow 10 ε of
            the reference, as IPOPT's do: near convergence φ changes by less than its rounding,
            and a filter entry must not block the very point it came from (a step that changed
            nothing, accepted at α ≈ 4e-9 on walk-to-fly, left an entry equal to the point in φ,
            and every later step from there was rejected)."""
            switching = (slope < 0) & (alpha * (-slope) ** 2.3 > theta0_**1.1) & (theta0_ <= state.theta_min)
            armijo = ph - phi0 - 1e-8 * alpha * slope <= rounding * jnp.abs(phi0)
            decrease = (th <= (1 - 1e-5) * theta0_) | (ph - phi0 + 1e-8 * theta0_ <= rounding * jnp.abs(phi0))
            filtered = in_filter(th, ph, filter_theta, filter_phi)
            sufficient = jnp.isfinite(th) & jnp.isfinite(ph) & jnp.where(switching, armijo, decrease)
            return sufficient & ~filtered, switching & armijo, sufficient & filtered

        rounding = _rounding(dtype)
        th1, ph1, c1 = trial(alpha_max, dP)
        ok1, f1, blocked1 = acceptable(alpha_max, th1, ph1)

        # Second-order corrections (IPOPT): when the full step raises the infeasibility, re-solve
        # with the constraint residual of the trial point folded in, up to SOC_STEPS times while
        # each correction cuts the infeasibility by κ_soc = 0.99. Judged with the full step's α.
        def correcting(carry):
            k, ok, _, th, th_old, _, _, _, _, _, _, _ = carry
            return (~ok) & (k < SOC_STEPS) & ((k == 0) | (th <= 0.99 * th_old))

        def correct(carry):
            k, _, _, th, _, c_soc, alpha_soc, c_trial, _, _, solves, blocked = carry
            c_soc = _tmap(lambda a, b: alpha_soc * a + b, c_soc, c_trial)
            step, alpha_soc, alpha_z_soc, more = direction(c_soc)
            th_soc, ph_soc, c_trial = trial(alpha_soc, step[0])
            ok, f_type, by_filter = acceptable(alpha_max, th_soc, ph_soc)
            return (k + 1, ok, f_type, th_soc, th, c_soc, alpha_soc, c_trial, step, alpha_z_soc, solves + more,
                    blocked | by_filter)

        try_soc = (~ok1) & (th1 >= theta0_) & factored
        _, soc_ok, soc_f, _, _, _, alpha_soc, _, soc_step, alpha_z_soc, solves, blocked = jax.lax.while_loop(
            correcting, correct,
            (jnp.where(try_soc, 0, SOC_STEPS), jnp.asarray(False), jnp.asarray(False), th1, th1, c, alpha_max, c1,
             newton, alpha_z, solves, blocked1),
        )

        def search(carry):
            alpha, _, _, count, blocked = carry
            alpha = alpha * 0.5
            th, ph, _ = trial(alpha, dP)
            ok, f_type, by_filter = acceptable(alpha, th, ph)
            return alpha, ok, f_type, count + 1, blocked | by_filter

        def keep_searching(carry):
            _, ok, _, count, _ = carry
            return (~ok) & (count < options.line_search_steps)

        alpha, accepted, f_type, _, blocked = jax.lax.while_loop(
            keep_searching, search,
            (alpha_max, ok1 | soc_ok, f1, jnp.where(soc_ok, options.line_search_steps, 0), blocked),
        )
        # The corrected step, when one was accepted, replaces the Newton step (duals included).
        dP, dy, dzl, dzu = jax.tree.map(lambda a, b: jnp.where(soc_ok, a, b), soc_step, newton)
        alpha = jnp.where(soc_ok, alpha_soc, alpha)
        alpha_z = jnp.where(soc_ok, alpha_z_soc, alpha_z)
        f_type = jnp.where(soc_ok, soc_f, f_type)
        accepted = accepted & factored & ~crawling
        # Soft restoration (IPOPT): every trial turned down, the Newton step to its
        # fraction-to-boundary length, in all variables at once, is taken if it reduces the
        # barrier problem's primal–dual error. Near a solution with huge multipliers (walk-to-fly),
        # Newton steps lower the infeasibility but raise φ, and the filter turns them all down.
        alpha_soft = jnp.minimum(alpha_max, alpha_z)

        def soft_trial(_):
            trial = [_tmap(lambda v, d: v + alpha_soft * d, v, d) for v, d in zip((P, y, zl, zu), newton)]
            # The current point's error from this iteration's blocks: a second reverse-mode pass
            # through the NLP costs ≈ 6 s of compilation.
            slack_dual = tuple(jnp.where(f, -yi * a - p + q, 0.0) for yi, a, p, q, f in
                               zip(y[2:], active, zl[2:], zu[2:], bounds.free[2:]))
            now = primal_dual_error(dual[:2] + slack_dual, c, complementarity(dl, du, zl, zu, mu))
            return primal_dual_error_at(*trial, mu) <= 0.9999 * now

        soft = jax.lax.cond(factored & ~accepted & ~crawling & (soft_steps < options.max_soft_steps), soft_trial,
                            lambda _: jnp.asarray(False), None)
        step = jnp.where(accepted, alpha, jnp.where(soft, alpha_soft, 0.0))
        step_z = jnp.where(accepted, alpha_z, jnp.where(soft, alpha_soft, 0.0))
        P_new = _tmap(lambda p, d: p + step * d, P, dP)
        y_new = _tmap(lambda v, d: v + step * d, y, dy)
        zl_new = _tmap(lambda v, d: v + step_z * d, zl, dzl)
        zu_new = _tmap(lambda v, d: v + step_z * d, zu, dzu)
        # Keep the bound multipliers within a factor κ_Σ = 1e10 of μ / distance (IPOPT).
        dl_new, du_new = _distances(P_new, bounds)
        zl_new = _tmap(lambda z, a, m: jnp.where(m, jnp.clip(z, mu / (1e10 * a), 1e10 * mu / a), 0.0),
                       zl_new, dl_new, bounds.has_lower)
        zu_new = _tmap(lambda z, b, m: jnp.where(m, jnp.clip(z, mu / (1e10 * b), 1e10 * mu / b), 0.0),
                       zu_new, du_new, bounds.has_upper)
        # The filter grows after every accepted step that was not an Armijo (f-type) step, and
        # with the iterate a soft restoration starts from (IPOPT).
        grow_filter = (accepted & ~f_type) | (soft & (soft_steps == 0))
        slot = filter_count % FILTER_SIZE
        filter_theta = jnp.where(grow_filter, filter_theta.at[slot].set((1 - 1e-5) * theta0_), filter_theta)
        filter_phi = jnp.where(grow_filter, filter_phi.at[slot].set(phi0 - 1e-8 * theta0_), filter_phi)
        filter_count = filter_count + grow_filter.astype(filter_count.dtype)
        # No step accepted, but one the filter alone turned down (the iterate has wandered into a
        # pocket its own history fences in): empty the filter and retry the step (IPOPT's filter
        # reset heuristic).
        unblock = factored & ~accepted & ~soft & ~crawling & blocked & (filter_resets < options.max_filter_resets)
        filter_theta = jnp.where(unblock, jnp.full_like(filter_theta, jnp.inf).at[0].set(state.theta_max), filter_theta)
        filter_phi = jnp.where(unblock, jnp.full_like(filter_phi, jnp.inf).at[0].set(-jnp.inf), filter_phi)
        filter_count = jnp.where(unblock, 1, filter_count)
        filter_resets = filter_resets + unblock.astype(filter_resets.dtype)
        moved = accepted | soft
        # Steps rejected max_rejections times in a row, each retried with more regularisation,
        # with the violation above tolerance: IPOPT's restoration phase, from here.
        restore = crawling | (~moved & ~unblock & (state.rejections + 1 >= options.max_rejections)
                              & (v_now > options.tolerance) & (options.max_restoration_iterations > 0))
        slot = filter_count % FILTER_SIZE
        filter_theta = jnp.where(restore, filter_theta.at[slot].set((1 - 1e-5) * theta0_), filter_theta)
        filter_phi = jnp.where(restore, filter_phi.at[slot].set(phi0 - 1e-8 * theta0_), filter_phi)
        filter_count = filter_count + restore.astype(filter_count.dtype)
        rejections = jnp.where(moved | unblock | restore, 0, state.rejections + 1)
        v_new, _ = violation(nlp, P_new[0], P_new[1])
        short = (step < options.short_step) & ~restore
        short_violation = jnp.where(short & (state.short_steps == 0), v_now, state.short_violation)
        short_steps = jnp.where(short & (v_new > 0.9 * short_violation), state.short_steps + 1, 0)
        record = jnp.stack([
            stagewise.residuals(nlp, P_new[0], P_new[1]).cost, v_new, error0, mu, step, delta_w, solves, 0.0,
            factorisations,
        ])
        status = jnp.where(
            converged, int(Status.CONVERGED),
            jnp.where(rejections < options.max_rejections, int(Status.RUNNING),
                      jnp.where(v_now > options.tolerance, int(Status.INFEASIBLE), int(Status.STALLED))),
        )
        new = State(
            P=P_new, y=y_new, zl=zl_new, zu=zu_new, mu=mu,
            regularisation=jnp.where(delta_w > 0, delta_w, state.regularisation),
            # A rejected step is retried from a more heavily regularised (shorter, steeper) one.
            forced=jnp.where(moved | unblock | restore, 0.0, jnp.maximum(delta_w * 100.0, 1e-4)),
            filter_theta=filter_theta, filter_phi=filter_phi, filter_count=filter_count, filter_resets=filter_resets,
            soft_steps=jnp.where(soft, soft_steps + 1, jnp.where(accepted, 0, soft_steps)),
            rejections=rejections, short_steps=short_steps, short_violation=short_violation,
            iterations=state.iterations + 1,
            barrier_updates=state.barrier_updates + updates, status=status, violation=v_new,
            stationarity=error0, history=state.history.at[state.iterations].set(record),
            scaling=state.scaling, theta_max=state.theta_max, theta_min=state.theta_min,
            restoring=restore,
            restoration_theta=jnp.where(restore, theta0_, state.restoration_theta),
            restoration_iterations=jnp.asarray(0),
        )
        # Converged: keep the point where the test held, not the step taken from it.
        new = jax.tree.map(lambda a, b: jnp.where(converged, b, a), new, dataclasses.replace(
            state, status=status, stationarity=error0, iterations=state.iterations + 1,
            history=state.history.at[state.iterations].set(
                jnp.stack([cost_now, v_now, error0, mu, 0.0, delta_w, 0.0, 0.0, factorisations]))))
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves((new.P, new.y, new.zl, new.zu))]))
        new = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, state)
        if options.progress is not None:  # the row the history keeps for this iteration
            jax.debug.callback(options.progress, state.iterations, new.history[state.iterations])
        return dataclasses.replace(new, status=jnp.where(finite, new.status, int(Status.NAN)),
                                   iterations=state.iterations + 1)

    def running(state):
        return (state.status == int(Status.RUNNING)) & (state.iterations < limit)

    return jax.lax.while_loop(running, body, state)


def finish(nlp, state, stopped=Status.MAX_ITERATIONS):
    """The ``Solution`` at ``state``; a solve still running is reported with status ``stopped``
    (an int, traced or not: ``MAX_ITERATIONS``, ``INTERRUPTED``, ``TIME_LIMIT``)."""
    cost_scale, row_scale = state.scaling[0], tuple(state.scaling[1])
    status = jnp.where(state.status == int(Status.RUNNING), jnp.asarray(stopped, state.status.dtype), state.status)
    Z, theta = state.P[0], state.P[1]
    v, per_group = violation(nlp, Z, theta)
    return Solution(
        Z=Z, theta=theta,
        multipliers=Multipliers(**{g: yi * s / cost_scale for g, yi, s in zip(GROUPS, state.y, row_scale)}),
        status=status, objective=stagewise.residuals(nlp, Z, theta).cost, violation=v,
        violation_per_group=per_group, stationarity=state.stationarity, iterations=state.iterations,
        barrier_updates=state.barrier_updates, history=state.history, bound_multipliers=(state.zl, state.zu),
        slacks=(state.P[2], state.P[3]), scaling=(cost_scale, row_scale),
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
