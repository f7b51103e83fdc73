"""IPOPT's filter (Wächter & Biegler 2006, section 2.4, eqs. 18–21): pairs (θ, φ) of
infeasibility ‖c‖₁ and barrier function that a trial point must improve on in one of the two, a
fixed ring of ``FILTER_SIZE`` entries."""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver.options import FILTER_SIZE
from jaxmm.solver.trees import select


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Filter:
    """theta, phi (FILTER_SIZE,): the entries (inf: unused); count: entries added since the
    last reset (the next one goes to slot count mod FILTER_SIZE); resets: filter resets since the
    barrier parameter last changed (``Options.max_filter_resets``)."""

    theta: jax.Array
    phi: jax.Array
    count: jax.Array
    resets: jax.Array


def rounding(dtype):
    """The relative allowance of the line search's comparisons: 10 ε, IPOPT's."""
    return 10 * jnp.finfo(dtype).eps


def empty(theta_max, resets=0):
    """A filter holding only the envelope θ ≤ theta_max (IPOPT's θ_max)."""
    theta_max = jnp.asarray(theta_max)
    return Filter(theta=jnp.full(FILTER_SIZE, jnp.inf, theta_max.dtype).at[0].set(theta_max),
                  phi=jnp.full(FILTER_SIZE, jnp.inf, theta_max.dtype).at[0].set(-jnp.inf),
                  count=jnp.asarray(1), resets=jnp.asarray(resets))


def augment(f, theta, phi, add):
    """``f`` with the entry ((1 − γ_θ) θ, φ − γ_φ θ) (γ = 1e-5, 1e-8, eq. 20) where ``add``."""
    slot = f.count % FILTER_SIZE
    return dataclasses.replace(
        f, theta=jnp.where(add, f.theta.at[slot].set((1 - 1e-5) * theta), f.theta),
        phi=jnp.where(add, f.phi.at[slot].set(phi - 1e-8 * theta), f.phi),
        count=f.count + jnp.asarray(add).astype(f.count.dtype))


def reset(f, theta_max, where, resets):
    """``f`` emptied to the envelope theta_max where ``where``, its reset counter set to ``resets``."""
    return select(where, empty(theta_max, resets), f)


def in_filter(theta, phi, filter_theta, filter_phi):
    """Whether (θ, φ) is rejected by the filter: worse than an entry in both, by more than 10 ε
    of that entry (IPOPT's comparison), so that no entry rejects the point it was made from."""
    allowance = rounding(filter_theta.dtype)
    tolerance = allowance * jnp.abs(jnp.where(jnp.isfinite(filter_phi), filter_phi, 0.0))
    return jnp.any((theta - filter_theta > allowance * filter_theta) & (phi - filter_phi > tolerance))
