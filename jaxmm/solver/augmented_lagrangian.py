"""An augmented-Lagrangian solver for stage-wise NLPs (``jaxmm.transcription.stagewise``).

Outer loop: Powell–Hestenes–Rockafellar augmented Lagrangian with safeguarded first-order
multiplier updates after every inner solve (ALGENCAN; Birgin & Martínez) and one penalty per
constraint row, each grown only when its own infeasibility–complementarity measure failed to
shrink by ``penalty_trigger`` (component-wise penalties, Conn, Gould & Toint). Rows of very
different units (forces in N next to positions in m) thus find their own penalty, and the
few stubborn rows do not make the whole Hessian stiff. Inequalities enter through the
projection form ρ/2 ‖g + μ/ρ − Π_[l,u](g + μ/ρ)‖²; variable boxes are kept exactly: every
iterate lies in the box.

Inner loop: Newton on the augmented Lagrangian over the box. The model uses the exact cost
Hessian blocks, ρ JᵀJ of the equality rows, the linearised inequality rows as penalised
piecewise-quadratic terms (their activity decided by the step, not frozen at the current point)
and (option ``curvature``, once the violation is below
``curvature_below``) the constraints' curvature Σ λᵢ ∇²cᵢ at the first-order multiplier
estimates. Far from feasibility that curvature, ρ c ∇²c, is large and indefinite and would force
huge regularisation, so the first iterations are Gauss–Newton; inertia is corrected by growing a
Levenberg–Marquardt δ until the block Cholesky succeeds. The step minimises the model
over the box (``box_qp``: semismooth projected Newton iterations that find the active sets), then an
Armijo search on the augmented Lagrangian. Every linear system is bordered block-tridiagonal and
is solved by ``linalg`` (block Cholesky in ``lax.scan`` plus a Schur complement for the
globals). The whole solve is one ``lax.while_loop``: it can be jitted and vmapped.
"""

import dataclasses
import enum
from typing import Callable

import jax
import jax.numpy as jnp

from jaxmm.solver import box_qp, linalg, rows
from jaxmm.transcription import stagewise


class Status(enum.IntEnum):
    """Why a solve stopped."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    STALLED = 2  # the penalty reached its cap, or no step decreases the merit: likely infeasible
    NAN = 3  # a non-finite value appeared; the last finite iterate is returned
    RUNNING = 4

    @property
    def message(self):
        return {
            Status.CONVERGED: "converged: feasibility and stationarity within tolerance",
            Status.MAX_ITERATIONS: "stopped at the iteration limit before converging",
            Status.STALLED: "stalled: the penalty reached its cap or no step reduces the merit (infeasible?)",
            Status.NAN: "a non-finite value appeared; returned the last finite iterate",
            Status.RUNNING: "running",
        }[self]


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings (static).

    tolerance: primal feasibility (max violation, in the NLP's scaled units);
    stationarity: ∞-norm of the projected gradient of the AL, whose cost is divided by
    max(1, ‖∇f(w₀)‖∞);
    max_outer, max_inner: iteration limits; max_iterations: total inner iterations;
    penalty0, penalty_growth, penalty_max: PHR penalty schedule, per row; penalty_trigger: a
    row's penalty grows when its infeasibility (with complementarity for inequalities) is above
    ``tolerance`` and above penalty_trigger × its value at the previous outer iteration; multiplier_max:
    safeguard on |y|; inner_tolerance0, inner_tightening: stationarity asked of the first inner
    solve and its factor per outer iteration; regularisation0, regularisation_max: LM δ;
    line_search_steps: Armijo halvings; qp_iterations: projected-Newton iterations of the box QP;
    curvature: add the constraints' curvature Σ yᵢ ∇²cᵢ (exact Hessian of the augmented
    Lagrangian up to the active-set kinks) to the Gauss–Newton matrix once the max violation
    is below ``curvature_below``;
    progress: called on the host after every inner iteration as progress(iteration, outer,
    record) with record the history row (``HISTORY_COLUMNS``); None (default) stays silent.
    """

    tolerance: float = 1e-6
    stationarity: float = 1e-6
    max_outer: int = 60
    max_inner: int = 50
    max_iterations: int = 2000
    penalty0: float = 10.0
    penalty_growth: float = 10.0
    penalty_max: float = 1e10
    penalty_trigger: float = 0.5
    multiplier_max: float = 1e12
    inner_tolerance0: float = 1e-1
    inner_tightening: float = 0.1
    regularisation0: float = 1e-8
    regularisation_max: float = 1e12
    line_search_steps: int = 30
    qp_iterations: int = 8
    curvature: bool = True
    curvature_below: float = 1e-2
    progress: Callable | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Multipliers:
    """Multipliers of every constraint group (same shapes as the residuals)."""

    path_equality: jax.Array
    transition_equality: jax.Array
    path_inequality: jax.Array
    transition_inequality: jax.Array


def _full_like_multipliers(nlp, Z, theta, value):
    r = stagewise.residuals(nlp, Z, theta)
    return Multipliers(**{group: jnp.full_like(getattr(r, group), value) for group in GROUPS})


GROUPS = ("path_equality", "transition_equality", "path_inequality", "transition_inequality")


def _projected(value, multiplier, penalty, lower, upper):
    """Shifted value, its projection and the new multiplier estimate of a two-sided constraint."""
    shifted = value + multiplier / penalty
    projection = jnp.clip(shifted, lower, upper)
    return shifted, projection, penalty * (shifted - projection)


def _terms(nlp, Z, theta, y, penalty):
    """Residuals and AL pieces: per group (value, new multiplier, active mask); ``penalty`` is a
    ``Multipliers``-shaped pytree of per-row penalties."""
    r = stagewise.residuals(nlp, Z, theta)
    out = {}
    for group in ("path_equality", "transition_equality"):
        value = getattr(r, group)
        out[group] = (value, getattr(y, group) + getattr(penalty, group) * value, jnp.ones_like(value))
    for group, lower, upper in (
        ("path_inequality", nlp.path_lower, nlp.path_upper),
        ("transition_inequality", nlp.transition_lower, nlp.transition_upper),
    ):
        value = getattr(r, group)
        shifted, projection, estimate = _projected(value, getattr(y, group), getattr(penalty, group), lower, upper)
        out[group] = (value, estimate, (shifted != projection).astype(value.dtype))
    return r.cost, out


def merit(nlp, Z, theta, y, penalty, cost_scale):
    """The augmented Lagrangian L_A(Z, θ; y, ρ) (scaled cost; ρ per row)."""
    cost, terms = _terms(nlp, Z, theta, y, penalty)
    value = cost_scale * cost
    for group, (_, estimate, _) in terms.items():
        value += jnp.sum((estimate**2 - getattr(y, group) ** 2) / (2 * getattr(penalty, group)))
    return value


def violation(nlp, Z, theta):
    """Max constraint violation over every group (scaled units) and per group."""
    r = stagewise.residuals(nlp, Z, theta)

    def outside(value, lower, upper):
        return jnp.maximum(jnp.maximum(lower - value, value - upper), 0.0)

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


def _newton_system(nlp, Z, theta, y, penalty, cost_scale, curvature=False):
    """The augmented Lagrangian's model at (Z, θ): the gradient (gz, gt) and Hessian blocks of
    the cost and the equality rows (Gauss–Newton, plus, when ``curvature`` (a traced bool), the
    constraints' curvature Σ λᵢ ∇²cᵢ at the first-order multiplier estimates λ = y + ρc,
    projected for inequalities); and the inequality rows as ``box_qp.PenaltyRows``, whose
    activity the step's model problem decides."""
    B = stagewise.blocks(nlp, Z, theta)
    _, terms = _terms(nlp, Z, theta, y, penalty)
    K = Z.shape[0]
    groups = {group: rows.Rows(*_group_jacobian(B, group)) for group in GROUPS}
    gz, gt = cost_scale * B.cost_z, cost_scale * B.cost_theta
    for group in ("path_equality", "transition_equality"):
        pz, pt = rows.pull(groups[group], terms[group][1], K)
        gz, gt = gz + pz, gt + pt
    hessian = rows.add(
        tuple(cost_scale * b for b in (B.cost_zz, jnp.zeros_like(B.cost_zz[1:]), B.cost_ztheta, B.cost_thetatheta)),
        *(rows.gram(groups[g], getattr(penalty, g), K) for g in ("path_equality", "transition_equality")),
    )

    def with_curvature(blocks):
        extra = stagewise.constraint_curvature(nlp, Z, theta, **{g: terms[g][1] for g in terms})
        return rows.add(blocks, extra)

    if curvature is not False:
        hessian = jax.lax.cond(curvature, with_curvature, lambda blocks: blocks, hessian)
    penalties = tuple(
        box_qp.PenaltyRows(
            rows=groups[group], shifted=terms[group][0] + getattr(y, group) / getattr(penalty, group),
            penalty=getattr(penalty, group), lower=lower, upper=upper,
        )
        for group, lower, upper in (
            ("path_inequality", nlp.path_lower, nlp.path_upper),
            ("transition_inequality", nlp.transition_lower, nlp.transition_upper),
        )
    )
    return (gz, gt), hessian, penalties


def _group_jacobian(B, group):
    """(jz, jt, jn) of a residual group from ``stagewise.blocks`` (jn None for path groups)."""
    if group.startswith("path"):
        return getattr(B, group + "_z"), getattr(B, group + "_theta"), None
    return getattr(B, group + "_z"), getattr(B, group + "_theta"), getattr(B, group + "_znext")


HISTORY_COLUMNS = ("merit", "violation", "stationarity", "penalty", "step_length", "regularisation")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """The solver's loop state (a pytree)."""

    Z: jax.Array
    theta: jax.Array
    multipliers: Multipliers
    penalty: Multipliers  # per-row penalties, same shapes
    previous_violation: Multipliers  # per-row infeasibility at the previous outer iteration
    inner_tolerance: jax.Array
    regularisation: jax.Array
    outer: jax.Array
    inner: jax.Array
    inner_this_outer: jax.Array
    iterations: jax.Array
    status: jax.Array
    violation: jax.Array
    stationarity: jax.Array
    history: jax.Array  # (max_iterations, 6): see ``HISTORY_COLUMNS``


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Solution:
    """Result of a solve: the optimum (scaled NLP variables), multipliers, why it stopped, and
    statistics. ``status`` is a ``Status`` code; ``history`` (max_iterations, 6) has one row per
    inner iteration with the columns of ``HISTORY_COLUMNS`` (penalty: the largest row's; step
    length 0: step rejected); rows past ``inner_iterations`` are NaN; ``penalty`` holds the
    per-row penalties (``Multipliers``-shaped)."""

    Z: jax.Array
    theta: jax.Array
    multipliers: Multipliers
    status: jax.Array
    objective: jax.Array
    violation: jax.Array
    violation_per_group: dict
    stationarity: jax.Array
    outer_iterations: jax.Array
    inner_iterations: jax.Array
    penalty: Multipliers
    history: jax.Array


def _largest(rows):
    return jnp.max(jnp.stack([jnp.max(leaf, initial=0.0) for leaf in jax.tree.leaves(rows)]))


def solve(nlp, Z0, theta0, options=Options(), multipliers=None):
    """Minimise the stage-wise NLP from (Z0 (K, nz), θ0 (ng,)); warm-start with ``multipliers``.

    Jittable and vmappable (options are static): ``jax.jit(solve, static_argnames="options")``.
    Returns a ``Solution``.
    """
    Z0, theta0 = jnp.clip(Z0, nlp.z_lower, nlp.z_upper), jnp.clip(theta0, nlp.theta_lower, nlp.theta_upper)
    y0 = _full_like_multipliers(nlp, Z0, theta0, 0.0) if multipliers is None else multipliers
    grad0 = stagewise.blocks(nlp, Z0, theta0)
    scale_ref = jnp.maximum(jnp.max(jnp.abs(grad0.cost_z)), jnp.max(jnp.abs(grad0.cost_theta)))
    cost_scale = 1.0 / jnp.maximum(1.0, scale_ref)
    v0, _ = violation(nlp, Z0, theta0)
    state = State(
        Z=Z0, theta=theta0, multipliers=y0, penalty=_full_like_multipliers(nlp, Z0, theta0, options.penalty0),
        previous_violation=_full_like_multipliers(nlp, Z0, theta0, jnp.inf),
        inner_tolerance=jnp.asarray(options.inner_tolerance0, Z0.dtype),
        regularisation=jnp.asarray(options.regularisation0, Z0.dtype),
        outer=jnp.asarray(0), inner=jnp.asarray(0), inner_this_outer=jnp.asarray(0),
        iterations=jnp.asarray(0), status=jnp.asarray(int(Status.RUNNING)),
        violation=v0, stationarity=jnp.asarray(jnp.inf, Z0.dtype),
        history=jnp.full((options.max_iterations, len(HISTORY_COLUMNS)), jnp.nan, Z0.dtype),
    )

    lower = (nlp.z_lower, nlp.theta_lower)
    upper = (nlp.z_upper, nlp.theta_upper)

    def project(Z, theta):
        return jnp.clip(Z, lower[0], upper[0]), jnp.clip(theta, lower[1], upper[1])

    def inner_step(state):
        y, rho = state.multipliers, state.penalty
        curvature = options.curvature and (state.violation < options.curvature_below)
        (gz, gt), (D, L, Bd, C), penalties = _newton_system(
            nlp, state.Z, state.theta, y, rho, cost_scale, curvature
        )
        model_gradient = (gz, gt)
        for p in penalties:
            pz, pt = rows.pull(p.rows, p.penalty * box_qp.excess(p), gz.shape[0])
            gz, gt = gz + pz, gt + pt
        # Projected gradient: the stationarity measure over the box.
        pz, pt = project(state.Z - gz, state.theta - gt)
        pz, pt = pz - state.Z, pt - state.theta
        stationarity = jnp.maximum(jnp.max(jnp.abs(pz)), jnp.max(jnp.abs(pt)))
        # Inertia correction without re-assembling: grow δ until H + δI is positive definite
        # (fixed variables, lo = hi, are left out).
        fz = (lower[0] != upper[0]).astype(gz.dtype)
        ft = (lower[1] != upper[1]).astype(gt.dtype)

        def regularised(delta):
            return (
                D + jax.vmap(jnp.diag)(delta * fz + 1.0 - fz), L, Bd,
                C + jnp.diag(delta * ft + 1.0 - ft),
            )

        def masked(hessian):
            D_, L_, B_, C_ = hessian
            return (
                fz[:, :, None] * D_ * fz[:, None, :] + jax.vmap(jnp.diag)(1.0 - fz),
                fz[1:, :, None] * L_ * fz[:-1, None, :],
                fz[:, :, None] * B_ * ft[None, None, :],
                ft[:, None] * C_ * ft[None, :] + jnp.diag(1.0 - ft),
            )

        # The inertia is checked with the inequality rows active here (their ρJᵀJ convexifies
        # the curvature their multipliers bring); the QP refactors as activity changes.
        active_rows = rows.add(
            *(rows.gram(p.rows, p.penalty * (box_qp.excess(p) != 0), gz.shape[0]) for p in penalties)
        )

        def definite(delta):
            return linalg.factor(*masked(rows.add(regularised(delta), active_rows))).ok

        def indefinite(carry):
            delta, ok = carry
            return (~ok) & (delta < options.regularisation_max)

        def stiffen(carry):
            delta, _ = carry
            delta = jnp.maximum(delta * 10.0, 1e-8)
            return delta, definite(delta)

        delta = state.regularisation
        delta, _ = jax.lax.while_loop(indefinite, stiffen, (delta, definite(delta)))
        # The Newton step: the model minimised over the box, its active sets found by the QP.
        (dz, dt), qp_ok = box_qp.solve(
            regularised(delta), model_gradient, (lower[0] - state.Z, lower[1] - state.theta),
            (upper[0] - state.Z, upper[1] - state.theta), options.qp_iterations, penalties,
        )
        base = merit(nlp, state.Z, state.theta, y, rho, cost_scale)

        def sufficient(value, decrease):
            return (value <= base + 1e-4 * decrease) & (decrease < 0) & jnp.isfinite(value)

        def try_step(alpha):
            Z, theta = project(state.Z + alpha * dz, state.theta + alpha * dt)
            decrease = jnp.sum(gz * (Z - state.Z)) + jnp.sum(gt * (theta - state.theta))
            return merit(nlp, Z, theta, y, rho, cost_scale), decrease

        def search(carry):
            alpha, _, _, count = carry
            value, decrease = try_step(alpha * 0.5)
            return alpha * 0.5, value, decrease, count + 1

        def keep_searching(carry):
            alpha, value, decrease, count = carry
            return (~sufficient(value, decrease)) & (count < options.line_search_steps)

        alpha, value, _, count = jax.lax.while_loop(keep_searching, search, (1.0, *try_step(1.0), 0))
        good = qp_ok & jnp.isfinite(value) & (count < options.line_search_steps)
        Z_new, theta_new = project(state.Z + alpha * dz, state.theta + alpha * dt)
        Z = jnp.where(good, Z_new, state.Z)
        theta = jnp.where(good, theta_new, state.theta)
        # LM schedule: relax after a full step, stiffen after a failed one.
        regularisation = jnp.where(
            good, jnp.maximum(delta / jnp.where(alpha == 1.0, 10.0, 1.0), 1e-12), delta * 100.0
        )
        regularisation = jnp.minimum(regularisation, options.regularisation_max)
        v, _ = violation(nlp, Z, theta)
        record = jnp.stack(
            [jnp.where(good, value, base), v, stationarity, _largest(rho), jnp.where(good, alpha, 0.0), delta]
        )
        if options.progress is not None:
            jax.debug.callback(options.progress, state.iterations, state.outer, record)
        return dataclasses.replace(
            state, Z=Z, theta=theta, regularisation=regularisation,
            inner=state.inner + 1, inner_this_outer=state.inner_this_outer + 1,
            iterations=state.iterations + 1, violation=v, stationarity=stationarity,
            history=state.history.at[state.iterations].set(record),
        ), good, stationarity

    def outer_update(state):
        """First-order multiplier update, safeguarded (ALGENCAN); a row's penalty grows only when
        its measure |y⁺ − y|/ρ (|c| for equalities; infeasibility and complementarity for
        inequalities) failed to shrink by ``penalty_trigger`` since the last outer iteration."""
        rho = state.penalty
        _, terms = _terms(nlp, state.Z, state.theta, state.multipliers, rho)
        v = state.violation
        bound = options.multiplier_max
        multipliers = Multipliers(**{group: jnp.clip(terms[group][1], -bound, bound) for group in GROUPS})
        measure = Multipliers(
            **{g: jnp.abs(terms[g][1] - getattr(state.multipliers, g)) / getattr(rho, g) for g in GROUPS}
        )
        failed = jax.tree.map(
            lambda m, previous: (m > options.penalty_trigger * previous) & (m > options.tolerance),
            measure, state.previous_violation,
        )
        new_rho = jax.tree.map(
            lambda r, f: jnp.where(f, jnp.minimum(r * options.penalty_growth, options.penalty_max), r), rho, failed
        )
        converged = (v <= options.tolerance) & (state.stationarity <= options.stationarity)
        stalled = jnp.any(jnp.stack([jnp.any(f & (r >= options.penalty_max)) for r, f in zip(
            jax.tree.leaves(rho), jax.tree.leaves(failed))]))
        status = jnp.where(converged, int(Status.CONVERGED), jnp.where(stalled, int(Status.STALLED), state.status))
        return dataclasses.replace(
            state, multipliers=multipliers, penalty=new_rho, previous_violation=measure,
            inner_tolerance=jnp.maximum(state.inner_tolerance * options.inner_tightening, options.stationarity),
            outer=state.outer + 1, inner_this_outer=jnp.asarray(0), status=status,
        )

    def body(state):
        new_state, good, stationarity = inner_step(state)
        finite = jnp.all(jnp.isfinite(new_state.Z)) & jnp.all(jnp.isfinite(new_state.theta))
        new_state = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_state, state)
        new_state = dataclasses.replace(
            new_state,
            status=jnp.where(finite, new_state.status, int(Status.NAN)),
            iterations=state.iterations + 1,
        )
        inner_done = (
            (new_state.stationarity <= new_state.inner_tolerance)
            | (new_state.inner_this_outer >= options.max_inner)
            | ((~good) & (new_state.regularisation >= options.regularisation_max))
        )
        return jax.lax.cond(
            inner_done & (new_state.status == int(Status.RUNNING)), outer_update, lambda s: s, new_state
        )

    def running(state):
        return (
            (state.status == int(Status.RUNNING))
            & (state.iterations < options.max_iterations)
            & (state.outer < options.max_outer)
        )

    state = jax.lax.while_loop(running, body, state)
    status = jnp.where(state.status == int(Status.RUNNING), int(Status.MAX_ITERATIONS), state.status)
    v, per_group = violation(nlp, state.Z, state.theta)
    return Solution(
        Z=state.Z, theta=state.theta, multipliers=state.multipliers, status=status,
        objective=stagewise.residuals(nlp, state.Z, state.theta).cost, violation=v,
        violation_per_group=per_group, stationarity=state.stationarity,
        outer_iterations=state.outer, inner_iterations=state.inner, penalty=state.penalty,
        history=state.history,
    )
