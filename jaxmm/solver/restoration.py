"""IPOPT's restoration phase (Wächter & Biegler 2006, section 3.3), with a least-squares
infeasibility measure: damped Gauss–Newton steps on ½‖c‖² within the bounds' barrier, until a
point acceptable to the filter is found.

The phase's step is the Newton step of ½‖c‖² + μ_R × barrier (μ_R = μ min(1, ‖c‖∞) /
RESTORATION_PENALTY, the cost left out) with the Gauss–Newton Hessian JᵀJ, damped by ζ D²
(ζ = √(μ / RESTORATION_PENALTY), D = min(1, 1/|P|), IPOPT's proximal weights): the same condensed
system, factorisation and solve as the barrier problem's (``newton``), with these terms instead
of the Lagrangian's, and the same loop of trials (``line_search``) with an Armijo test on the
measure. The phase ends, as IPOPT's, at a point that the filter (which holds the point the phase
started from) accepts and whose infeasibility ‖c‖₁ is at most 0.9 of that point's, or at such a
point within the violation tolerance, the filter then emptied (``outcome``); it fails (status
``INFEASIBLE``, or ``STALLED`` at a point within the violation tolerance) when no step decreases
its measure (a locally infeasible point) or after ``max_restoration_iterations``. Back in the
barrier problem the constraint multipliers start from 0 (IPOPT's default) and the bound
multipliers on its central path (μ / distance)."""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver import barrier, filter as filters, rows
from jaxmm.solver.options import RESTORATION_PENALTY, Status
from jaxmm.solver.trees import dot, l1, max_abs, select, tmap


def terms(state, c, b):
    """(μ_R, ζ, D² per primal leaf) of the phase at ``state`` with scaled residuals c. The
    barrier's weight shrinks with the infeasibility, as the gradient of ½‖c‖² does (IPOPT's ℓ1
    measure keeps its gradient): entered at a violation of 2e-6, a fixed μ / 1000 let the barrier
    push walk-to-fly's active bounds apart, the violation up to 1e-3 and the objective from 6.2e7
    to 1.8e9 in 100 iterations."""
    mu = state.mu / RESTORATION_PENALTY * jnp.minimum(1.0, max_abs(c))
    zeta = jnp.sqrt(state.mu / RESTORATION_PENALTY)
    D2 = tmap(lambda r, f: jnp.where(f, jnp.minimum(1.0, 1.0 / jnp.maximum(jnp.abs(r), 1e-300)) ** 2, 0.0),
              state.iterate.P, b.free)
    return mu, zeta, D2


def measure(c, log_sum, mu):
    """½‖c‖² + μ × barrier, from the barrier's Σ ln(distance)."""
    return 0.5 * dot(c, c) - mu * log_sum


def slope(c, J, direction, active, bgrad):
    """The measure's directional derivative along a ``line_search.Direction``."""
    linear = tuple(rows.apply(r, *direction.dx) for r in J)
    linear = linear[:2] + tuple(jnp.where(a, v - d, 0.0) for v, d, a in zip(linear[2:], direction.ds, active))
    return dot(c, linear) + dot(bgrad, direction.dP)


def outcome(problem, options, state, step):
    """The state after one iteration of the phase (``step``: the iteration's ``Step``) and its
    history row."""
    b, it, search = problem.bounds, state.iterate, step.search
    mu = step.mu_step
    found = step.factored & (search.slope < 0) & search.accepted
    d = search.newton
    step_z = jnp.where(found, d.alpha_z, 0.0)
    # Without a step the point stays and so do its residuals.
    P_new, r_new, c_new = select(found, (search.last.P, search.last.r, search.last.c), (it.P, state.residuals, step.c))
    f_new = jnp.where(found, search.last.f, step.f_now)
    zl_new, zu_new = barrier.safeguard(tmap(lambda z, v: z + step_z * v, it.zl, d.dzl),
                                       tmap(lambda z, v: z + step_z * v, it.zu, d.dzu), P_new, mu, b)
    theta_new = l1(c_new)
    phi_new = f_new + barrier.value(P_new, b, state.mu)
    v_new, _ = problem.violation(P_new, r_new)
    reduced = found & (theta_new <= 0.9 * state.restoration_theta)
    blocked = filters.in_filter(theta_new, phi_new, state.filter.theta, state.filter.phi)
    # A point within the violation tolerance that the filter still turns down (it holds points of
    # less violation and lower merit from before the phase) ends the phase with the filter
    # emptied, IPOPT's filter reset heuristic, at most max_filter_resets times per μ. With the
    # resets spent, walk-to-fly's exact task spent 100 iterations at such a point (violation 5.5e-7).
    within = v_new <= options.tolerance
    feasible = reduced & blocked & within & (state.filter.resets < options.max_filter_resets)
    done = reduced & (~blocked | feasible)
    count = state.counters.restoration_iterations + 1
    failed = ~done & (~found | (count >= options.max_restoration_iterations))
    # Back in the barrier problem, the bound multipliers start on its central path.
    dl_new, du_new = barrier.distances(P_new, b)
    zl_new = tmap(lambda z, a, m: jnp.where(done & m, state.mu / a, z), zl_new, dl_new, b.has_lower)
    zu_new = tmap(lambda z, c, m: jnp.where(done & m, state.mu / c, z), zu_new, du_new, b.has_upper)
    K = P_new[0].shape[0]
    record = jnp.stack([r_new.cost, v_new, state.stationarity, state.mu, jnp.where(found, search.last.alpha, 0.0),
                        step.zeta, 1.0, 1.0, step.work.astype(v_new.dtype) / K])
    counters = dataclasses.replace(state.counters, soft_steps=jnp.zeros_like(state.counters.soft_steps),
                                   rejections=jnp.zeros_like(state.counters.rejections),
                                   short_steps=jnp.zeros_like(state.counters.short_steps), restoration_iterations=count)
    new = dataclasses.replace(
        state, iterate=dataclasses.replace(it, P=P_new, zl=zl_new, zu=zu_new,
                                           y=jax.tree.map(lambda v: jnp.where(done, 0.0, v), it.y)),
        residuals=r_new, restoring=~done, counters=counters,
        filter=filters.reset(state.filter, state.theta_max, feasible, state.filter.resets + 1),
        # A phase that fails at a point within the violation tolerance stopped feasible.
        status=jnp.where(failed, jnp.where(within, int(Status.STALLED), int(Status.INFEASIBLE)), int(Status.RUNNING)),
        violation=v_new,
        # The regularisation escalated by the rejected steps before the phase is forgotten.
        forced=jnp.zeros_like(state.forced), regularisation=jnp.zeros_like(state.regularisation))
    return new, record
