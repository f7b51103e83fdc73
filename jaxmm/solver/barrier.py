"""The bounds' logarithmic barrier (Fiacco & McCormick) and IPOPT's rules around it: the bound
push of a starting point, the primal–dual barrier terms Σ = Z/distance, the bound multipliers'
steps, the fraction-to-boundary rule and the κ_Σ safeguard (Wächter & Biegler 2006, eqs. 11,
15, 16). Everything acts on tuples of primal leaves (Z, θ, path slacks, transition slacks)."""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver.options import KAPPA_SIGMA
from jaxmm.solver.trees import flat, tmap


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Bounds:
    """Bounds of the primal leaves (Z, θ, path slacks, transition slacks) and their masks."""

    lower: tuple
    upper: tuple
    has_lower: tuple  # finite lower bound on a non-fixed entry
    has_upper: tuple
    free: tuple  # not fixed (lower < upper)


def bounds(nlp, slack_scale):
    """``Bounds`` of (Z, θ, path slacks, transition slacks); a slack is in the row's scaled units
    (slack_scale: the two inequality groups' row factors)."""
    lower = (nlp.z_lower, nlp.theta_lower, nlp.path_lower * slack_scale[0], nlp.transition_lower * slack_scale[1])
    upper = (nlp.z_upper, nlp.theta_upper, nlp.path_upper * slack_scale[0], nlp.transition_upper * slack_scale[1])
    free = tuple(lo < hi for lo, hi in zip(lower, upper))
    has_lower = tuple(jnp.isfinite(lo) & f for lo, f in zip(lower, free))
    has_upper = tuple(jnp.isfinite(hi) & f for hi, f in zip(upper, free))
    return Bounds(lower, upper, has_lower, has_upper, free)


def distances(P, b):
    """Distances (to lower, to upper) of P to its finite bounds (1 where there is none)."""
    dl = tuple(jnp.where(m, p - lo, 1.0) for p, lo, m in zip(P, b.lower, b.has_lower))
    du = tuple(jnp.where(m, hi - p, 1.0) for p, hi, m in zip(P, b.upper, b.has_upper))
    return dl, du


def log_sum(P, b):
    """Σ ln(distance) over the finite bounds (the barrier is −μ times this)."""
    dl, du = distances(P, b)
    return jnp.sum(flat(tmap(lambda a, c, ml, mu_: jnp.where(ml, jnp.log(a), 0.0) + jnp.where(mu_, jnp.log(c), 0.0),
                             dl, du, b.has_lower, b.has_upper)))


def value(P, b, mu):
    """The barrier −μ Σ ln(distance) over the finite bounds."""
    return -mu * log_sum(P, b)


def interior(P, b, kappa=1e-2):
    """P moved strictly inside its bounds (IPOPT's bound push κ₁ = κ₂ = kappa, eq. 36)."""

    def push(p, lo, hi, ml, mu_, free):
        width = jnp.where(ml & mu_, hi - lo, jnp.inf)
        pl = jnp.minimum(kappa * jnp.maximum(1.0, jnp.abs(jnp.where(ml, lo, 0.0))), kappa * width)
        pu = jnp.minimum(kappa * jnp.maximum(1.0, jnp.abs(jnp.where(mu_, hi, 0.0))), kappa * width)
        p = jnp.where(ml, jnp.maximum(p, lo + pl), p)
        p = jnp.where(mu_, jnp.minimum(p, hi - pu), p)
        return jnp.where(free, p, lo)

    return tmap(push, P, b.lower, b.upper, b.has_lower, b.has_upper, b.free)


def fraction_to_boundary(values, steps, tau):
    """Largest α ≤ 1 keeping every value (distance or multiplier) ≥ (1 − τ) of itself (eq. 15)."""
    ratios = tmap(lambda v, d: jnp.where(d < 0, -tau * v / jnp.where(d < 0, d, -1.0), jnp.inf), values, steps)
    return jnp.minimum(1.0, jnp.min(flat(ratios), initial=jnp.inf))


def terms(dl, du, zl, zu, mu, b):
    """(Σ, the primal–dual barrier Hessian, and the barrier gradient) per primal leaf, from the
    distances to the bounds (dl, du) and the bound multipliers (zl, zu)."""
    sigma = tmap(lambda a, c, p, q, ml, mu_: jnp.where(ml, p / a, 0.0) + jnp.where(mu_, q / c, 0.0),
                 dl, du, zl, zu, b.has_lower, b.has_upper)
    gradient = tmap(lambda a, c, ml, mu_: jnp.where(ml, -mu / a, 0.0) + jnp.where(mu_, mu / c, 0.0),
                    dl, du, b.has_lower, b.has_upper)
    return sigma, gradient


def bound_steps(dl, du, zl, zu, dP, mu, tau, b):
    """The bound multipliers' Newton steps (dzl, dzu) for the primal step dP (eq. 11), and the
    fraction-to-boundary lengths (τ) of the primal and of the multiplier steps."""
    dzl = tmap(lambda a, p, d, m: jnp.where(m, mu / a - p - p * d / a, 0.0), dl, zl, dP, b.has_lower)
    dzu = tmap(lambda c, q, d, m: jnp.where(m, mu / c - q + q * d / c, 0.0), du, zu, dP, b.has_upper)
    alpha_max = fraction_to_boundary(
        dl + du, tmap(lambda d, m: jnp.where(m, d, 0.0), dP, b.has_lower)
        + tmap(lambda d, m: jnp.where(m, -d, 0.0), dP, b.has_upper), tau)
    return dzl, dzu, alpha_max, fraction_to_boundary(zl + zu, dzl + dzu, tau)


def complementarity(dl, du, zl, zu, mu, b):
    """distance · z − μ per bound (0 where there is none), lower bounds' leaves first."""
    return tmap(lambda a, z, m: jnp.where(m, a * z - mu, 0.0), dl + du, zl + zu, b.has_lower + b.has_upper)


def safeguard(zl, zu, P, mu, b):
    """The bound multipliers kept within a factor κ_Σ of μ / distance at P (eq. 16), 0 where
    there is no bound."""
    dl, du = distances(P, b)
    clip = lambda z, a, m: jnp.where(m, jnp.clip(z, mu / (KAPPA_SIGMA * a), KAPPA_SIGMA * mu / a), 0.0)  # noqa: E731
    return tmap(clip, zl, dl, b.has_lower), tmap(clip, zu, du, b.has_upper)
