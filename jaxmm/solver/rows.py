"""Linearised constraint rows of a stage-wise NLP, and their products with step vectors.

A group of rows is either *path* rows, one set per knot acting on (z_k, θ), or *transition*
rows, one set per interval acting on (z_k, z_{k+1}, θ). ``Rows`` holds their Jacobians; the
functions below apply J and Jᵀ and form the Gram blocks Jᵀ W J in the bordered
block-tridiagonal layout of ``linalg`` (diagonal D, sub-diagonal L, border B, corner C).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Rows:
    """Jacobians of one group: jz (R, m, n) w.r.t. the row's knot, jn (R, m, n) w.r.t. the next
    knot (transition rows; None for path rows, R = K), jt (R, m, ng) w.r.t. the globals;
    supports (static, optional): the group's ``stagewise.RowSupport`` partition of its m rows,
    which ``gram`` exploits; scale (R, m) (optional): each row's factor, the rows being
    scale ⊙ (jz, jn, jt) (``scaled``)."""

    jz: jax.Array
    jt: jax.Array
    jn: jax.Array | None = None
    supports: tuple | None = dataclasses.field(default=None, metadata=dict(static=True))
    scale: jax.Array | None = None


def group_rows(blocks, group, supports=None):
    """The ``Rows`` of one constraint group ("path_equality", …) of a ``stagewise.Blocks``, with
    the group's row supports (from ``StagewiseFunctions.row_supports``) checked to partition
    its rows."""
    jz, jt = getattr(blocks, group + "_z"), getattr(blocks, group + "_theta")
    jn = None if group.startswith("path") else getattr(blocks, group + "_znext")
    if supports is not None:
        supports = tuple(supports)
        m, n = jz.shape[-2:]
        runs = [(s.start, s.stop) for s in supports]
        if [a for a, _ in runs] != [0] + [b for _, b in runs[:-1]] or (runs[-1][1] if runs else 0) != m:
            raise ValueError(f"row supports of {group} must cover its {m} rows in consecutive runs, got {runs}")
        for s in supports:
            columns = np.asarray(tuple(s.now) + tuple(s.next), dtype=int)
            if columns.size and (columns.min() < 0 or columns.max() >= n):
                raise ValueError(f"row supports of {group}: a column outside 0..{n - 1} in rows {s.start}:{s.stop}")
            if jn is None and len(s.next):
                raise ValueError(f"row supports of {group}: path rows cannot depend on the next knot")
    return Rows(jz, jt, jn, supports)


def scaled(rows, scale):
    """The rows times scale (R, m), row by row: the factor is kept beside the Jacobians
    (``Rows.scale``) and applied to the row vectors, not to the Jacobians (a pass over them)."""
    return dataclasses.replace(rows, scale=scale if rows.scale is None else rows.scale * scale)


def _scale(rows, v):
    """v (R, m) times the rows' factors."""
    return v if rows.scale is None else v * rows.scale


def apply(rows, dz, dt):
    """J d: (R, m) for a step dz (K, n), dt (ng,)."""
    if rows.jn is None:
        out = jnp.einsum("kmn,kn->km", rows.jz, dz)
    else:
        out = jnp.einsum("kmn,kn->km", rows.jz, dz[:-1]) + jnp.einsum("kmn,kn->km", rows.jn, dz[1:])
    return _scale(rows, out + jnp.einsum("kmg,g->km", rows.jt, dt))


def pull(rows, v, K):
    """Jᵀ v for row weights v (R, m): (gz (K, n), gt (ng,))."""
    v = _scale(rows, v)
    if rows.jn is None:
        gz = jnp.einsum("kmn,km->kn", rows.jz, v)
    else:
        n = rows.jz.shape[-1]
        gz = jnp.zeros((K, n), v.dtype)
        gz = gz.at[:-1].add(jnp.einsum("kmn,km->kn", rows.jz, v))
        gz = gz.at[1:].add(jnp.einsum("kmn,km->kn", rows.jn, v))
    return gz, jnp.einsum("kmg,km->g", rows.jt, v)


def gram(rows, w, K, into=None):
    """Blocks (D, L, B, C) of Jᵀ diag(w) J for row weights w (R, m); with ``into`` (blocks
    (D, L, B, C) of the same shapes), those plus ``into``, the products added into its blocks
    (separate arrays, summed after, cost a pass over the (K, n, n) blocks each).

    With ``rows.supports`` the knot blocks are formed run by run on the run's columns alone
    (on iRonCub ≈ 3 % of a dense block's products)."""
    jz, jt = rows.jz, rows.jt
    n, ng = jz.shape[-1], jt.shape[-1]
    w = _scale(rows, _scale(rows, w))
    if into is None:
        into = (jnp.zeros((K, n, n), w.dtype), jnp.zeros((K - 1, n, n), w.dtype), jnp.zeros((K, n, ng), w.dtype),
                jnp.zeros((ng, ng), w.dtype))
    D, L, B, C = (jnp.asarray(b) for b in into)
    C = C + jnp.einsum("kmg,km,kmh->gh", jt, w, jt)
    if rows.supports is not None:
        return _sparse_gram(rows, w, D, L, B) + (C,)
    if rows.jn is None:
        return D + jnp.einsum("kma,km,kmb->kab", jz, w, jz), L, B + jnp.einsum("kma,km,kmg->kag", jz, w, jt), C
    jn = rows.jn
    D = D.at[:-1].add(jnp.einsum("kma,km,kmb->kab", jz, w, jz))
    D = D.at[1:].add(jnp.einsum("kma,km,kmb->kab", jn, w, jn))
    B = B.at[:-1].add(jnp.einsum("kma,km,kmg->kag", jz, w, jt))
    B = B.at[1:].add(jnp.einsum("kma,km,kmg->kag", jn, w, jt))
    return D, L + jnp.einsum("kma,km,kmb->kab", jn, w, jz), B, C


def grams(groups, weights, K, into=None):
    """Σ of ``gram`` over the groups (a sequence of ``Rows``) and their row weights, each added
    into the previous one's blocks (and into ``into``'s, if given)."""
    for r, w in zip(groups, weights):
        into = gram(r, w, K, into=into)
    return into


def _sparse_gram(rows, w, D, L, B):
    """(D, L, B) plus ``gram``'s products, from the row supports: per run, the products of its
    columns only; all runs' products added into each of D and L by one scatter (one per run
    compiled a scatter kernel each, 39 on iRonCub)."""
    jz, jt, jn = rows.jz, rows.jt, rows.jn
    transition = jn is not None
    knots = slice(None, -1) if transition else slice(None)
    now_parts, next_parts, coupling_parts = [], [], []
    for s in rows.supports:
        now, following = np.asarray(s.now, dtype=int), np.asarray(s.next, dtype=int)
        if s.stop == s.start:
            continue
        ws = w[:, s.start:s.stop]
        a = jz[:, s.start:s.stop][:, :, now]
        now_parts.append((jnp.einsum("kma,km,kmb->kab", a, ws, a), now, now))
        if transition and following.size:
            b = jn[:, s.start:s.stop][:, :, following]
            next_parts.append((jnp.einsum("kma,km,kmb->kab", b, ws, b), following, following))
            coupling_parts.append((jnp.einsum("kma,km,kmb->kab", b, ws, a), following, now))
    D = _add_blocks(_add_blocks(D, knots, now_parts), slice(1, None), next_parts)
    L = _add_blocks(L, slice(None), coupling_parts)
    # The border is n × ng per knot: dense is as cheap as any gather.
    B = B.at[knots].add(jnp.einsum("kma,km,kmg->kag", jz, w, jt))
    if transition:
        B = B.at[1:].add(jnp.einsum("kma,km,kmg->kag", jn, w, jt))
    return D, L, B


def _add_blocks(X, knots, parts):
    """X (R, n, n) with each part's products (R', r, c) added at its rows × columns (static) of
    the knots ``knots``, by one scatter-add."""
    if not parts:
        return X
    values = jnp.concatenate([p.reshape(p.shape[0], -1) for p, _, _ in parts], axis=1)
    rows = np.concatenate([np.repeat(r, len(c)) for _, r, c in parts])
    columns = np.concatenate([np.tile(c, len(r)) for _, r, c in parts])
    return X.at[knots, rows, columns].add(values)


def coupled_columns(supports):
    """The columns of z_k in which the sub-diagonal blocks L (∂²/∂z_{k+1}∂z_k of any Newton
    matrix built from the constraints) can be non-zero: the union of the transition groups'
    ``now`` columns, as a sorted tuple (``linalg.factor``'s ``coupled``); None, meaning every
    column, when a transition group declares no supports. supports: {group: tuple of
    ``RowSupport``}."""
    groups = ("transition_equality", "transition_inequality")
    if any(supports.get(g) is None for g in groups):
        return None
    columns = set()
    for g in groups:
        for run in supports[g]:
            columns.update(int(c) for c in run.now)
    return tuple(sorted(columns))


def add(*blocks):
    """Sum of (D, L, B, C) tuples."""
    return tuple(sum(parts) for parts in zip(*blocks))
