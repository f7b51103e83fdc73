"""Linearised constraint rows of a stage-wise NLP, and their products with step vectors.

A group of rows is either *path* rows, one set per knot acting on (z_k, θ), or *transition*
rows, one set per interval acting on (z_k, z_{k+1}, θ). ``Rows`` holds their Jacobians; the
functions below apply J and Jᵀ and form the Gram blocks Jᵀ W J in the bordered
block-tridiagonal layout of ``linalg`` (diagonal D, sub-diagonal L, border B, corner C).
"""

import dataclasses

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Rows:
    """Jacobians of one group: jz (R, m, n) w.r.t. the row's knot, jn (R, m, n) w.r.t. the next
    knot (transition rows; None for path rows, R = K), jt (R, m, ng) w.r.t. the globals."""

    jz: jax.Array
    jt: jax.Array
    jn: jax.Array | None = None


def apply(rows, dz, dt):
    """J d: (R, m) for a step dz (K, n), dt (ng,)."""
    if rows.jn is None:
        out = jnp.einsum("kmn,kn->km", rows.jz, dz)
    else:
        out = jnp.einsum("kmn,kn->km", rows.jz, dz[:-1]) + jnp.einsum("kmn,kn->km", rows.jn, dz[1:])
    return out + jnp.einsum("kmg,g->km", rows.jt, dt)


def pull(rows, v, K):
    """Jᵀ v for row weights v (R, m): (gz (K, n), gt (ng,))."""
    if rows.jn is None:
        gz = jnp.einsum("kmn,km->kn", rows.jz, v)
    else:
        n = rows.jz.shape[-1]
        gz = jnp.zeros((K, n), v.dtype)
        gz = gz.at[:-1].add(jnp.einsum("kmn,km->kn", rows.jz, v))
        gz = gz.at[1:].add(jnp.einsum("kmn,km->kn", rows.jn, v))
    return gz, jnp.einsum("kmg,km->g", rows.jt, v)


def gram(rows, w, K):
    """Blocks (D, L, B, C) of Jᵀ diag(w) J for row weights w (R, m)."""
    jz, jt = rows.jz, rows.jt
    n, ng = jz.shape[-1], jt.shape[-1]
    C = jnp.einsum("kmg,km,kmh->gh", jt, w, jt)
    if rows.jn is None:
        D = jnp.einsum("kma,km,kmb->kab", jz, w, jz)
        return D, jnp.zeros((K - 1, n, n), w.dtype), jnp.einsum("kma,km,kmg->kag", jz, w, jt), C
    jn = rows.jn
    D = jnp.zeros((K, n, n), w.dtype)
    D = D.at[:-1].add(jnp.einsum("kma,km,kmb->kab", jz, w, jz))
    D = D.at[1:].add(jnp.einsum("kma,km,kmb->kab", jn, w, jn))
    B = jnp.zeros((K, n, ng), w.dtype)
    B = B.at[:-1].add(jnp.einsum("kma,km,kmg->kag", jz, w, jt))
    B = B.at[1:].add(jnp.einsum("kma,km,kmg->kag", jn, w, jt))
    return D, jnp.einsum("kma,km,kmb->kab", jn, w, jz), B, C


def add(*blocks):
    """Sum of (D, L, B, C) tuples."""
    return tuple(sum(parts) for parts in zip(*blocks))
