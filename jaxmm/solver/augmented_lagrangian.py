"""An augmented-Lagrangian solver for stage-wise NLPs (``jaxmm.transcription.stagewise``).

Outer loop: Powell–Hestenes–Rockafellar augmented Lagrangian with the multiplier and penalty
schedule of LANCELOT (Conn, Gould, Toint): when the constraint violation meets the current
feasibility tolerance the multipliers are updated and both tolerances tighten; otherwise the
penalty grows and the multipliers are kept. Inequalities enter through the projection form
ρ/2 ‖g + μ/ρ − Π_[l,u](g + μ/ρ)‖²; variable boxes are kept exactly (as LANCELOT does): every
iterate lies in the box.

Inner loop: projected Newton on the augmented Lagrangian over the box (Bertsekas' projected
Newton): exact cost Hessian blocks, the constraints' curvature weighted by the multiplier
estimates, and ρ JᵀJ of the active rows, with the variables
held at a bound removed from the step, Levenberg–Marquardt regularisation and an Armijo search
along the projection arc. Each Newton system is bordered block-tridiagonal and is solved by
``linalg`` (block Cholesky in ``lax.scan`` plus a Schur complement for the globals). The whole
solve is one ``lax.while_loop``: it can be jitted and vmapped.
"""

import dataclasses
import enum

import jax
import jax.numpy as jnp

from jaxmm.solver import linalg
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
    stationarity: ∞-norm of the AL gradient relative to max(1, ‖∇f(w₀)‖∞);
    max_outer, max_inner: iteration limits; max_iterations: total inner iterations;
    penalty0, penalty_growth, penalty_max: PHR penalty schedule; regularisation0: initial LM δ;
    curvature: add the constraints' curvature Σ yᵢ ∇²cᵢ (exact Hessian of the augmented
    Lagrangian up to the active-set kinks) to the Gauss–Newton matrix; on take-off N = 10 it
    turns 1/100 steps into full steps.
    """

    tolerance: float = 1e-6
    stationarity: float = 1e-6
    max_outer: int = 60
    max_inner: int = 50
    max_iterations: int = 2000
    penalty0: float = 10.0
    penalty_growth: float = 10.0
    penalty_max: float = 1e10
    regularisation0: float = 1e-8
    line_search_steps: int = 30
    curvature: bool = True


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
    """Gradient and Hessian blocks of the augmented Lagrangian (Gauss–Newton, plus the
    constraints' curvature when ``curvature``)."""
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
        f, a = nlp.functions, nlp.args
        nz_, ng_ = Z.shape[1], theta.shape[0]

        def path_curvature(function, weights):
            def weighted(w, y_k):
                return jnp.sum(function(a, w[:nz_], w[nz_:]) * y_k)

            return jax.vmap(jax.hessian(weighted))(jnp.concatenate([Z, jnp.broadcast_to(theta, (Z.shape[0], ng_))], 1), weights)

        def transition_curvature(function, weights):
            def weighted(w, y_k):
                return jnp.sum(function(a, w[:nz_], w[nz_ : 2 * nz_], w[2 * nz_ :]) * y_k)

            stacked = jnp.concatenate([Z[:-1], Z[1:], jnp.broadcast_to(theta, (Z.shape[0] - 1, ng_))], 1)
            return jax.vmap(jax.hessian(weighted))(stacked, weights)

        for group, function in (("path_equality", f.path_equality), ("path_inequality", f.path_inequality)):
            H = path_curvature(function, terms[group][1])
            D += H[:, :nz_, :nz_]
            Bd += H[:, :nz_, nz_:]
            C += jnp.sum(H[:, nz_:, nz_:], axis=0)
        for group, function in (
            ("transition_equality", f.transition_equality),
            ("transition_inequality", f.transition_inequality),
        ):
            H = transition_curvature(function, terms[group][1])
            D = D.at[:-1].add(H[:, :nz_, :nz_]).at[1:].add(H[:, nz_ : 2 * nz_, nz_ : 2 * nz_])
            L += H[:, nz_ : 2 * nz_, :nz_]
            Bd = Bd.at[:-1].add(H[:, :nz_, 2 * nz_ :]).at[1:].add(H[:, nz_ : 2 * nz_, 2 * nz_ :])
            C += jnp.sum(H[:, 2 * nz_ :, 2 * nz_ :], axis=0)

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
    feasibility_tolerance: jax.Array
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
        feasibility_tolerance=jnp.asarray(0.1, Z0.dtype) / penalty0**0.1,
        inner_tolerance=1.0 / penalty0,
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
        # ε-active bounds (Bertsekas): at a bound with the gradient pushing outwards, or fixed.
        eps = jnp.minimum(1e-3, stationarity)

        def free(w, g, lo, hi):
            held = ((w <= lo + eps) & (g > 0)) | ((w >= hi - eps) & (g < 0)) | (lo == hi)
            return (~held).astype(w.dtype)

        fz, ft = free(state.Z, gz, lower[0], upper[0]), free(state.theta, gt, lower[1], upper[1])
        delta = state.regularisation
        D_free = fz[:, :, None] * D * fz[:, None, :] + jax.vmap(jnp.diag)(1.0 - fz + delta * fz)
        L_free = fz[1:, :, None] * L * fz[:-1, None, :]
        B_free = fz[:, :, None] * Bd * ft[None, None, :]
        C_free = ft[:, None] * C * ft[None, :] + jnp.diag(1.0 - ft + delta * ft)
        chol = linalg.factor(D_free, L_free, B_free, C_free)
        dz, dt = linalg.solve(chol, -gz * fz, -gt * ft)
        # Held variables follow the projected gradient instead of staying put.
        dz = dz * fz + (1.0 - fz) * pz
        dt = dt * ft + (1.0 - ft) * pt
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
        good = chol.ok & jnp.isfinite(value) & (count < options.line_search_steps)
        Z_new, theta_new = project(state.Z + alpha * dz, state.theta + alpha * dt)
        Z = jnp.where(good, Z_new, state.Z)
        theta = jnp.where(good, theta_new, state.theta)
        # LM schedule: relax after a full step, stiffen after a failed one.
        regularisation = jnp.where(
            good, jnp.maximum(delta / jnp.where(alpha == 1.0, 10.0, 1.0), 1e-12), delta * 100.0
        )
        v, _ = violation(nlp, Z, theta)
        record = jnp.stack(
            [jnp.where(good, value, base), v, stationarity, rho, jnp.where(good, alpha, 0.0), delta]
        )
        return dataclasses.replace(
            state, Z=Z, theta=theta, regularisation=jnp.minimum(regularisation, 1e12),
            inner=state.inner + 1, inner_this_outer=state.inner_this_outer + 1,
            iterations=state.iterations + 1, violation=v, stationarity=stationarity,
            history=state.history.at[state.iterations].set(record),
        ), good, stationarity

    def outer_update(state):
        """Multiplier update or penalty increase (LANCELOT), then convergence tests."""
        rho = state.penalty
        _, terms = _terms(nlp, state.Z, state.theta, state.multipliers, rho)
        v, _ = violation(nlp, state.Z, state.theta)
        updated = Multipliers(**{group: terms[group][1] for group in terms})
        feasible_enough = v <= state.feasibility_tolerance
        multipliers = jax.tree.map(lambda new, old: jnp.where(feasible_enough, new, old), updated, state.multipliers)
        new_rho = jnp.where(feasible_enough, rho, jnp.minimum(rho * options.penalty_growth, options.penalty_max))
        feas_tol = jnp.where(
            feasible_enough, state.feasibility_tolerance / new_rho**0.9, 0.1 / new_rho**0.1
        )
        inner_tol = jnp.where(feasible_enough, state.inner_tolerance / new_rho, 1.0 / new_rho)
        converged = (v <= options.tolerance) & (state.stationarity <= options.stationarity)
        stalled = (~feasible_enough) & (rho >= options.penalty_max)
        status = jnp.where(converged, int(Status.CONVERGED), jnp.where(stalled, int(Status.STALLED), state.status))
        return dataclasses.replace(
            state, multipliers=multipliers, penalty=new_rho,
            feasibility_tolerance=jnp.maximum(feas_tol, options.tolerance),
            inner_tolerance=jnp.maximum(inner_tol, options.stationarity),
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
            | ((~good) & (new_state.regularisation >= 1e12))
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
