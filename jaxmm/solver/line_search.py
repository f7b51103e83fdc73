"""IPOPT's filter line search (Wächter & Biegler 2006, section 2.3–2.4 and 3.3–3.4) as one loop of
trials: the Newton step at its fraction-to-boundary length, then second-order corrections
(when the full step raised the infeasibility), then backtracking; and, when every trial was
turned down, the soft-restoration point (the Newton step at its fraction-to-boundary length in
the primal and the dual variables, IPOPT's soft restoration), evaluated by the same loop so that
its residuals come with it. The same loop evaluates the starting point of a solve (phase
EVALUATE: one trial at P itself, judged by nobody), so that no other call site of the NLP's
functions is compiled.

Each pass of the loop computes at most one direction (the Newton step, or a correction: the
same ``direction`` call, its right-hand side chosen by the phase) and evaluates one trial point,
so the block solve and the NLP's functions appear once in the compiled program. The restoration
phase runs the same loop with its own acceptance test (an Armijo decrease of its measure) and no
corrections."""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver.options import SOC_STEPS
from jaxmm.solver.trees import select, tmap

NEWTON, CORRECTION, BACKTRACK, SOFT, DONE, EVALUATE = 0, 1, 2, 3, 4, 5


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Direction:
    """A step of the primal–dual iterate: dP (per primal leaf), dy (per group), dzl, dzu (bound
    multipliers), alpha_max and alpha_z (their fraction-to-boundary lengths), dx = (dz, dt) and
    ds (the step's variable and slack parts: dP = dx + ds), solves (block solves it took)."""

    dP: tuple
    dy: tuple
    dzl: tuple
    dzu: tuple
    alpha_max: jax.Array
    alpha_z: jax.Array
    dx: tuple
    ds: tuple
    solves: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trial:
    """A trial point P + α dP: the point, its scaled cost f and residuals c, the NLP's residuals
    r, and its step length α."""

    P: tuple
    f: jax.Array
    c: tuple
    r: object
    alpha: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Search:
    """The loop's state: phase (NEWTON, CORRECTION, BACKTRACK, SOFT, DONE, EVALUATE); newton, the
    Newton direction; correction, the last second-order correction and its right-hand side c_soc (the
    accumulated residuals, eq. 27 of Wächter & Biegler) with its step length alpha_soc;
    corrections, backtracks: their counts; slope, the directional derivative of the merit along
    the Newton step; last, the last trial and theta_last its infeasibility; accepted, f_type
    (an Armijo step of the filter method), corrected (the accepted trial was a correction),
    blocked (some trial was rejected by the filter alone); soft (every trial was turned down and
    last is the soft-restoration point); solves (block solves in all)."""

    phase: jax.Array
    newton: Direction
    correction: Direction
    c_soc: tuple
    alpha_soc: jax.Array
    corrections: jax.Array
    backtracks: jax.Array
    slope: jax.Array
    last: Trial
    theta_last: jax.Array
    accepted: jax.Array
    f_type: jax.Array
    corrected: jax.Array
    blocked: jax.Array
    soft: jax.Array
    solves: jax.Array


def _zero_direction(P, c):
    """A zero ``Direction`` for the primal leaves P (Z, θ, slacks…) and the rows' residuals c
    (its structure, without tracing a block solve)."""
    dP, dy = tmap(jnp.zeros_like, P), tmap(jnp.zeros_like, c)
    zero = jnp.zeros((), P[0].dtype)
    return Direction(dP, dy, dP, dP, zero, zero, dP[:2], dP[2:], jnp.asarray(0))


def filter_acceptance(alpha, theta, phi, theta0, phi0, slope, theta_min, in_filter, rounding):
    """(accepted, an Armijo step (f-type), rejected by the filter alone) of a trial with
    infeasibility θ and barrier function φ, for a step length α from (θ₀, φ₀) with slope ∇φᵀd
    (IPOPT's switching condition, Armijo condition and sufficient decrease, eqs. 19–21).
    Comparisons allow 10 ε of the reference, as IPOPT's do: near convergence φ changes by less
    than its rounding, and a filter entry must not block the very point it came from (a step
    that changed nothing, accepted at α ≈ 4e-9 on walk-to-fly, left an entry equal to the point
    in φ, and every later step from there was rejected)."""
    switching = (slope < 0) & (alpha * (-slope) ** 2.3 > theta0**1.1) & (theta0 <= theta_min)
    armijo = phi - phi0 - 1e-8 * alpha * slope <= rounding * jnp.abs(phi0)
    decrease = (theta <= (1 - 1e-5) * theta0) | (phi - phi0 + 1e-8 * theta0 <= rounding * jnp.abs(phi0))
    filtered = in_filter(theta, phi)
    sufficient = jnp.isfinite(theta) & jnp.isfinite(phi) & jnp.where(switching, armijo, decrease)
    return sufficient & ~filtered, switching & armijo, sufficient & filtered


def search(P, c, r, direction, evaluate, judge, slope_of, theta_of, restoring, start, steps, soft, evaluate_only=False):
    """The trials of one iteration from P (scaled residuals c there; r: the NLP's residuals at P,
    or any of their structure, kept as the last trial's until one is evaluated).

    direction(c_q, needed) → ``Direction`` for the constraint right-hand side c_q (a zero step
    without a block solve where ``needed`` is false); evaluate(P) → (f, c, r); slope_of(Direction) → the merit's
    slope; judge(α_judge, α, trial, θ, slope) → (accepted, f_type, by the filter alone);
    theta_of(c) → ‖c‖₁; restoring: no corrections (the restoration phase); start: whether to
    search at all (the Newton matrix factored); steps: most backtracking halvings; soft: whether
    the soft-restoration point P + min(α_max, α_z) dP follows when every trial is turned down;
    evaluate_only (where ``start`` is false): one trial at P itself, not accepted, so that
    ``last`` holds the residuals at P (the first pass of a solve, ``state.FirstPass``).
    Returns the final ``Search``."""
    theta0 = theta_of(c)

    def body(s):
        first, correcting, backtracking = s.phase == NEWTON, s.phase == CORRECTION, s.phase == BACKTRACK
        softening, evaluating = s.phase == SOFT, s.phase == EVALUATE
        c_next = tmap(lambda a, b: s.alpha_soc * a + b, s.c_soc, s.last.c)
        d = direction(select(first, c, c_next), first | correcting)
        newton = select(first, d, s.newton)
        slope = jax.lax.cond(first, slope_of, lambda _: s.slope, d)
        alpha = jnp.where(backtracking, 0.5 * s.last.alpha,
                          jnp.where(softening, jnp.minimum(s.newton.alpha_max, s.newton.alpha_z), d.alpha_max))
        dP = select(backtracking | softening, s.newton.dP, d.dP)
        Pt = select(evaluating, P, tmap(lambda p, v: p + alpha * v, P, dP))
        f, ct, rt = evaluate(Pt)
        theta = theta_of(ct)
        ok, f_type, by_filter = judge(jnp.where(backtracking, alpha, newton.alpha_max), alpha, (Pt, f, ct), theta, slope)
        judged = ~softening & ~evaluating
        ok, f_type, by_filter = ok & judged, f_type & judged, by_filter & judged
        # Second-order corrections (IPOPT's max_soc, κ_soc = 0.99): when the full step raises the
        # infeasibility, and again while each correction cuts it by κ_soc.
        to_correction = ~ok & ~restoring & ((first & (theta >= theta0))
                                            | (correcting & (s.corrections + 1 < SOC_STEPS) & (theta <= 0.99 * s.theta_last)))
        to_backtrack = ~ok & ~to_correction & ~softening & jnp.where(backtracking, s.backtracks + 1 < steps, steps > 0)
        to_soft = ~ok & ~to_correction & ~to_backtrack & ~softening & soft
        phase = jnp.where(to_correction, CORRECTION, jnp.where(to_backtrack, BACKTRACK, jnp.where(to_soft, SOFT, DONE)))
        phase = jnp.where(evaluating, DONE, phase)
        last = Trial(Pt, f, ct, rt, jnp.where(to_backtrack & ~backtracking, newton.alpha_max, alpha))
        return Search(
            phase=phase, newton=newton, correction=select(correcting, d, s.correction),
            c_soc=select(first, c, select(correcting, c_next, s.c_soc)),
            alpha_soc=jnp.where(first | correcting, d.alpha_max, s.alpha_soc),
            corrections=s.corrections + correcting, backtracks=s.backtracks + backtracking, slope=slope,
            last=last, theta_last=jnp.where(softening, s.theta_last, theta), accepted=ok, f_type=f_type,
            corrected=correcting & ok, blocked=s.blocked | by_filter, soft=softening, solves=s.solves + d.solves)

    blank = _zero_direction(P, c)
    zero = jnp.zeros((), theta0.dtype)
    initial = Search(
        phase=jnp.where(start, NEWTON, jnp.where(evaluate_only, EVALUATE, DONE)), newton=blank, correction=blank,
        c_soc=c, alpha_soc=zero,
        corrections=jnp.asarray(0), backtracks=jnp.asarray(0), slope=zero,
        last=Trial(P, zero, c, r, zero),
        theta_last=theta0, accepted=jnp.asarray(False), f_type=jnp.asarray(False), corrected=jnp.asarray(False),
        blocked=jnp.asarray(False), soft=jnp.asarray(False), solves=jnp.zeros_like(blank.solves))
    return jax.lax.while_loop(lambda s: s.phase != DONE, body, initial)
