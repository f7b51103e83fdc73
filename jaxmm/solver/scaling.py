"""The NLP as the solver sees it: IPOPT's gradient-based scaling of the cost and of every row
(no gradient above ``Options.max_gradient``, fixed at the starting point), the inequality rows as
equalities g − s = 0 with a slack s, and the constraint violation in the NLP's own units."""

import dataclasses

import jax.numpy as jnp

from jaxmm import stagewise
from jaxmm.solver import barrier, rows
from jaxmm.solver.options import GROUPS


def outside(value, lower, upper):
    """Distance of value to [lower, upper] (0 inside)."""
    return jnp.maximum(jnp.maximum(lower - value, value - upper), 0.0)


def relaxed(nlp, path, transition, sigma):
    """The inequality rows path (K, mg) and transition (K − 1, mh) with the bounds that ``nlp``
    marks widened by σ (the NLP's units; None: none): g − sign · σ, so that the bound g ≤ u + σ
    reads g − σ ≤ u (Scholtes' relaxation, ``StagewiseNLP.path_relaxation``)."""
    if nlp.path_relaxation is None or sigma is None:
        return path, transition
    return path - sigma * nlp.path_relaxation, transition - sigma * nlp.transition_relaxation


def violation(nlp, Z, theta, r=None, sigma=None):
    """Max constraint violation over every group (the NLP's units) and per group; ``r``: the
    residuals at (Z, θ) when they are at hand; σ: the relaxation of the marked rows' bounds
    (``relaxed``), None for the NLP itself."""
    r = stagewise.residuals(nlp, Z, theta) if r is None else r
    path, transition = relaxed(nlp, r.path_inequality, r.transition_inequality, sigma)
    groups = dict(
        path_equality=jnp.abs(r.path_equality),
        transition_equality=jnp.abs(r.transition_equality),
        path_inequality=outside(path, nlp.path_lower, nlp.path_upper),
        transition_inequality=outside(transition, nlp.transition_lower, nlp.transition_upper),
        z_box=outside(Z, nlp.z_lower, nlp.z_upper),
        theta_box=outside(theta, nlp.theta_lower, nlp.theta_upper),
    )
    per_group = {k: jnp.max(v, initial=0.0) for k, v in groups.items()}
    return jnp.max(jnp.stack(list(per_group.values()))), per_group


def row_scale(r, max_gradient):
    """IPOPT's gradient-based row scaling: min(1, max_gradient / ‖∇cᵢ‖∞) per row of the ``Rows`` r."""
    largest = jnp.maximum(jnp.max(jnp.abs(r.jz), axis=-1, initial=0.0), jnp.max(jnp.abs(r.jt), axis=-1, initial=0.0))
    if r.jn is not None:
        largest = jnp.maximum(largest, jnp.max(jnp.abs(r.jn), axis=-1, initial=0.0))
    return jnp.minimum(1.0, max_gradient / jnp.maximum(largest, 1e-300))


def scaling(B, max_gradient):
    """(cost factor, per-row factors of the four groups) from the ``stagewise.Blocks`` B at the
    starting point: IPOPT's gradient-based scaling, no row or cost gradient above max_gradient."""
    cost_scale = jnp.minimum(1.0, max_gradient / jnp.maximum(
        jnp.maximum(jnp.max(jnp.abs(B.cost_z)), jnp.max(jnp.abs(B.cost_theta))), 1e-300))
    return cost_scale, tuple(row_scale(rows.group_rows(B, g), max_gradient) for g in GROUPS)


@dataclasses.dataclass(frozen=True)
class ScaledProblem:
    """The stage-wise ``nlp`` in the solver's units: cost × cost_scale, rows × row_scale (the
    four groups' (R, m) factors), inequality rows g − s with the slacks s in scaled units;
    ``active``: the inequality rows with a finite bound (the others constrain nothing: their
    slack follows g); ``bounds``: the primal leaves' ``barrier.Bounds``; sigma: the relaxation σ
    of the marked rows' bounds (``relaxed``) in the NLP's units, None for the NLP itself."""

    nlp: stagewise.StagewiseNLP
    cost_scale: jnp.ndarray
    row_scale: tuple
    active: tuple
    bounds: barrier.Bounds
    sigma: jnp.ndarray | None = None

    def constraints(self, P, r):
        """The scaled equality residuals (c, g − s) of the four groups at P = (Z, θ, slacks),
        from the NLP's residuals r there."""
        s = self.row_scale
        path, transition = relaxed(self.nlp, r.path_inequality, r.transition_inequality, self.sigma)
        return (
            r.path_equality * s[0],
            r.transition_equality * s[1],
            (path * s[2] - P[2]) * self.active[0],
            (transition * s[3] - P[3]) * self.active[1],
        )

    def violation(self, P, r):
        """The violation (``violation``) of the relaxed NLP at P, from its residuals r."""
        return violation(self.nlp, P[0], P[1], r, self.sigma)

    def evaluate(self, P):
        """(scaled cost, scaled residuals (``constraints``), the NLP's ``stagewise.Residuals``) at P."""
        r = stagewise.residuals(self.nlp, P[0], P[1])
        return self.cost_scale * r.cost, self.constraints(P, r), r


def scaled_problem(nlp, factors, sigma=None):
    """The ``ScaledProblem`` of ``nlp`` with factors = (cost factor, per-row factors) and the
    relaxation σ of its marked rows."""
    cost_scale, row_factors = factors[0], tuple(factors[1])
    active = (
        jnp.broadcast_to(jnp.isfinite(nlp.path_lower) | jnp.isfinite(nlp.path_upper), row_factors[2].shape),
        jnp.broadcast_to(jnp.isfinite(nlp.transition_lower) | jnp.isfinite(nlp.transition_upper), row_factors[3].shape),
    )
    return ScaledProblem(nlp, cost_scale, row_factors, active, barrier.bounds(nlp, row_factors[2:]), sigma)
