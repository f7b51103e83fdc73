"""An augmented-Lagrangian solver for stage-wise NLPs (``jaxmm.transcription.stagewise``).

Outer loop: Powell–Hestenes–Rockafellar augmented Lagrangian with safeguarded first-order
multiplier updates after every inner solve and a penalty that grows only when the violation
failed to shrink by ``penalty_trigger`` (ALGENCAN; Birgin & Martínez). Inequalities enter
through the projection form ρ/2 ‖g + μ/ρ − Π_[l,u](g + μ/ρ)‖²; variable boxes are kept exactly:
every iterate lies in the box.

Inner loop: Newton on the augmented Lagrangian over the box. The model uses the exact cost
Hessian blocks, ρ JᵀJ of the active rows and (option ``curvature``) the constraints' curvature
Σ λᵢ ∇²cᵢ at the first-order multiplier estimates; inertia is corrected by growing a
Levenberg–Marquardt δ until the block Cholesky succeeds. The step solves the model's
box-constrained QP (``box_qp``: projected Newton iterations that find the active set), then an
Armijo search on the augmented Lagrangian. Every linear system is bordered block-tridiagonal and
is solved by ``linalg`` (block Cholesky in ``lax.scan`` plus a Schur complement for the
globals). The whole solve is one ``lax.while_loop``: it can be jitted and vmapped.
"""

import dataclasses
import enum
from typing import Callable

import jax
import jax.numpy as jnp

from jaxmm.solver import box_qp, linalg
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
    penalty0, penalty_growth, penalty_max: PHR penalty schedule; penalty_trigger: the penalty
    grows when violation > penalty_trigger × the previous outer iteration's; multiplier_max:
    safeguard on |y|; inner_tolerance0, inner_tightening: stationarity asked of the first inner
    solve and its factor per outer iteration; regularisation0, regularisation_max: LM δ;
    line_search_steps: Armijo halvings; qp_iterations: projected-Newton iterations of the box QP;
    curvature: add the constraints' curvature Σ yᵢ ∇²cᵢ (exact Hessian of the augmented
    Lagrangian up to the active-set kinks) to the Gauss–Newton matrix;
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
    progress: Callable | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Multipliers:
    """Multipliers of every constraint group (same shapes as the residuals)."""

    path_equality: jax.Array
    transition_equality: jax.Array
    path_inequality: jax.Array
    transition_inequality: jax.Array


def _zeros_like_multipliers(nlp, Z, theta):
    r = stagewise.residuals(nlp, Z, theta)
    return Multipliers(
        path_equality=jnp.zeros_like(r.path_equality),
        transition_equality=jnp.zeros_like(r.transition_equality),
        path_inequality=jnp.zeros_like(r.path_inequality),
        transition_inequality=jnp.zeros_like(r.transition_inequality),
    )


def _projected(value, multiplier, penalty, lower, upper):
    """Shifted value, its projection and the new multiplier estimate of a two-sided constraint."""
    shifted = value + multiplier / penalty
    projection = jnp.clip(shifted, lower, upper)
    return shifted, projection, penalty * (shifted - projection)


def _terms(nlp, Z, theta, y, penalty):
    """Residuals and AL pieces: per group (value, new multiplier, active mask)."""
    r = stagewise.residuals(nlp, Z, theta)
    out = dict(
        path_equality=(r.path_equality, y.path_equality + penalty * r.path_equality, jnp.ones_like(r.path_equality)),
        transition_equality=(
            r.transition_equality,
            y.transition_equality + penalty * r.transition_equality,
            jnp.ones_like(r.transition_equality),
        ),
    )
    for group, lower, upper, value in (
        ("path_inequality", nlp.path_lower, nlp.path_upper, r.path_inequality),
        ("transition_inequality", nlp.transition_lower, nlp.transition_upper, r.transition_inequality),
    ):
        shifted, projection, estimate = _projected(value, getattr(y, group), penalty, lower, upper)
        out[group] = (value, estimate, (shifted != projection).astype(value.dtype))
    return r.cost, out


def merit(nlp, Z, theta, y, penalty, cost_scale):
    """The augmented Lagrangian L_A(Z, θ; y, ρ) (scaled cost)."""
    cost, terms = _terms(nlp, Z, theta, y, penalty)
    value = cost_scale * cost
    for group, (_, estimate, _) in terms.items():
        value += (jnp.sum(estimate**2) - jnp.sum(getattr(y, group) ** 2)) / (2 * penalty)
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
    """Gradient and Hessian blocks of the augmented Lagrangian: Gauss–Newton, plus (when
    ``curvature``) the constraints' curvature Σ λᵢ ∇²cᵢ weighted by the first-order multiplier
    estimates λ = y + ρc (projected for inequalities): the exact Hessian up to the kinks."""
    B = stagewise.blocks(nlp, Z, theta)
    _, terms = _terms(nlp, Z, theta, y, penalty)
    K, nz = Z.shape
    grad_z = cost_scale * B.cost_z
    grad_t = cost_scale * B.cost_theta
    D = cost_scale * B.cost_zz
    L = jnp.zeros((K - 1, nz, nz))
    Bd = cost_scale * B.cost_ztheta
    C = cost_scale * B.cost_thetatheta

    def path(group, Jz, Jt):
        nonlocal grad_z, grad_t, D, Bd, C
        _, estimate, active = terms[group]
        w = penalty * active
        grad_z += jnp.einsum("kmn,km->kn", Jz, estimate)
        grad_t += jnp.einsum("kmg,km->g", Jt, estimate)
        D += jnp.einsum("kma,km,kmb->kab", Jz, w, Jz)
        Bd += jnp.einsum("kma,km,kmg->kag", Jz, w, Jt)
        C += jnp.einsum("kmg,km,kmh->gh", Jt, w, Jt)

    def transition(group, Jz, Jn, Jt):
        nonlocal grad_z, grad_t, D, L, Bd, C
        _, estimate, active = terms[group]
        w = penalty * active
        grad_z = grad_z.at[:-1].add(jnp.einsum("kmn,km->kn", Jz, estimate))
        grad_z = grad_z.at[1:].add(jnp.einsum("kmn,km->kn", Jn, estimate))
        grad_t += jnp.einsum("kmg,km->g", Jt, estimate)
        D = D.at[:-1].add(jnp.einsum("kma,km,kmb->kab", Jz, w, Jz))
        D = D.at[1:].add(jnp.einsum("kma,km,kmb->kab", Jn, w, Jn))
        L += jnp.einsum("kma,km,kmb->kab", Jn, w, Jz)
        Bd = Bd.at[:-1].add(jnp.einsum("kma,km,kmg->kag", Jz, w, Jt))
        Bd = Bd.at[1:].add(jnp.einsum("kma,km,kmg->kag", Jn, w, Jt))
        C += jnp.einsum("kmg,km,kmh->gh", Jt, w, Jt)

    if curvature:
        Dc, Lc, Bc, Cc = stagewise.constraint_curvature(nlp, Z, theta, **{g: terms[g][1] for g in terms})
        D, L, Bd, C = D + Dc, L + Lc, Bd + Bc, C + Cc

    path("path_equality", B.path_equality_z, B.path_equality_theta)
    path("path_inequality", B.path_inequality_z, B.path_inequality_theta)
    transition("transition_equality", B.transition_equality_z, B.transition_equality_znext, B.transition_equality_theta)
    transition(
        "transition_inequality", B.transition_inequality_z, B.transition_inequality_znext, B.transition_inequality_theta
    )
    return (grad_z, grad_t), (D, L, Bd, C)


HISTORY_COLUMNS = ("merit", "violation", "stationarity", "penalty", "step_length", "regularisation")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """The solver's loop state (a pytree)."""

    Z: jax.Array
    theta: jax.Array
    multipliers: Multipliers
    penalty: jax.Array
    previous_violation: jax.Array
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
    inner iteration with the columns of ``HISTORY_COLUMNS`` (step length 0: step rejected); rows
    past ``inner_iterations`` are NaN."""

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
    penalty: jax.Array
    history: jax.Array


def solve(nlp, Z0, theta0, options=Options(), multipliers=None):
    """Minimise the stage-wise NLP from (Z0 (K, nz), θ0 (ng,)); warm-start with ``multipliers``.

    Jittable and vmappable (options are static): ``jax.jit(solve, static_argnames="options")``.
    Returns a ``Solution``.
    """
    Z0, theta0 = jnp.clip(Z0, nlp.z_lower, nlp.z_upper), jnp.clip(theta0, nlp.theta_lower, nlp.theta_upper)
    y0 = _zeros_like_multipliers(nlp, Z0, theta0) if multipliers is None else multipliers
    grad0 = stagewise.blocks(nlp, Z0, theta0)
    scale_ref = jnp.maximum(jnp.max(jnp.abs(grad0.cost_z)), jnp.max(jnp.abs(grad0.cost_theta)))
    cost_scale = 1.0 / jnp.maximum(1.0, scale_ref)
    penalty0 = jnp.asarray(options.penalty0, dtype=Z0.dtype)
    v0, _ = violation(nlp, Z0, theta0)
    state = State(
        Z=Z0, theta=theta0, multipliers=y0, penalty=penalty0,
        previous_violation=jnp.asarray(jnp.inf, Z0.dtype),
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
        (gz, gt), (D, L, Bd, C) = _newton_system(nlp, state.Z, state.theta, y, rho, cost_scale, options.curvature)
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

        def indefinite(carry):
            delta, ok = carry
            return (~ok) & (delta < options.regularisation_max)

        def stiffen(carry):
            delta, _ = carry
            delta = jnp.maximum(delta * 10.0, 1e-8)
            return delta, linalg.factor(*masked(regularised(delta))).ok

        delta = state.regularisation
        delta, _ = jax.lax.while_loop(indefinite, stiffen, (delta, linalg.factor(*masked(regularised(delta))).ok))
        # The Newton step: the box-constrained QP of the model, its active set found by the QP.
        (dz, dt), qp_ok = box_qp.solve(
            regularised(delta), (gz, gt), (lower[0] - state.Z, lower[1] - state.theta),
            (upper[0] - state.Z, upper[1] - state.theta), options.qp_iterations,
        )
        base = merit(nlp, state.Z, state.theta, y, rho, cost_scale)

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
            sufficient = (value <= base + 1e-4 * decrease) & (decrease < 0)
            return (~(sufficient & jnp.isfinite(value))) & (count < options.line_search_steps)

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
            [jnp.where(good, value, base), v, stationarity, rho, jnp.where(good, alpha, 0.0), delta]
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
        """First-order multiplier update, safeguarded (ALGENCAN); the penalty grows only when
        the violation failed to shrink by ``penalty_trigger`` since the last outer iteration."""
        rho = state.penalty
        _, terms = _terms(nlp, state.Z, state.theta, state.multipliers, rho)
        v = state.violation
        bound = options.multiplier_max
        multipliers = Multipliers(**{group: jnp.clip(terms[group][1], -bound, bound) for group in terms})
        failed = (v > options.penalty_trigger * state.previous_violation) & (v > options.tolerance)
        new_rho = jnp.where(failed, jnp.minimum(rho * options.penalty_growth, options.penalty_max), rho)
        converged = (v <= options.tolerance) & (state.stationarity <= options.stationarity)
        stalled = failed & (rho >= options.penalty_max)
        status = jnp.where(converged, int(Status.CONVERGED), jnp.where(stalled, int(Status.STALLED), state.status))
        return dataclasses.replace(
            state, multipliers=multipliers, penalty=new_rho, previous_violation=v,
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
