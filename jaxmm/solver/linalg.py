"""Block-tridiagonal symmetric positive-definite systems with a dense border.

    [ D_0   L_1ᵀ                 B_0     ] [x_0]   [r_0]
    [ L_1   D_1   L_2ᵀ           B_1     ] [x_1]   [r_1]
    [       ⋱     ⋱     ⋱        ⋮       ] [ ⋮ ] = [ ⋮ ]
    [             L_{K−1} D_{K−1} B_{K−1} ] [   ]   [   ]
    [ B_0ᵀ  B_1ᵀ   …     B_{K−1}ᵀ C       ] [y  ]   [s  ]

The block Cholesky factorisation runs forward in a ``jax.lax.while_loop`` (a Riccati-like recursion,
O(K n³)); the border (the global variables) is eliminated by a Schur complement. No dense
factorisation of the whole matrix is ever formed. A matrix that is not positive definite
stops the factorisation at its first failing block: ``BlockCholesky.ok`` reports it.

When the coupling blocks L_k are non-zero only in some columns (``coupled``: of a stage-wise
NLP, the variables of knot k that its transition rows touch), each knot's variables are
ordered with those columns last: the Schur update of the next block then involves only them
(a triangular solve with s right-hand sides on the trailing s × s factor and an (n × s)(s × n)
product, instead of n × n ones).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BlockCholesky:
    """A = 𝓛 𝓛ᵀ with 𝓛 block lower-bidiagonal, each knot's variables in the order ``order``
    (static; the coupled columns last): diagonal (K, n, n), the trailing s columns of the
    sub-diagonal (K − 1, n, s); plus the border's Schur complement factor (m, m), A⁻¹B
    (K, n, m), and the number of diagonal blocks factored (K unless a block was not positive
    definite: the blocks after that one are 0)."""

    diagonal: jax.Array
    subdiagonal: jax.Array
    border_solution: jax.Array
    schur: jax.Array
    border: jax.Array
    factored: jax.Array
    order: tuple = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def ok(self):
        """True when every block was factored and every factor is finite (the matrix was
        positive definite)."""
        return (self.factored == self.diagonal.shape[-3]) & jnp.all(jnp.isfinite(self.schur))


def _factor_tridiagonal(D, L, order, s, shift):
    """Block Cholesky of the tridiagonal part, D's diagonals plus ``shift`` (K, n), with each
    knot's variables in the order ``order`` (static (n,) indices; None: as given), L's columns
    non-zero only in the last s of that order (``coupled_order``): returns (Lc (K, n, n),
    W (K − 1, n, s), the number of diagonal blocks factored before the first that is not
    positive definite), in that order."""
    K, n = D.shape[:2]
    if order is None:
        block, coupling = (lambda k: D[k] + jnp.diag(shift[k])), (lambda k: L[k])
    else:
        # Reordered block by block, in cache: reordering the (K, n, n) arrays up front cost
        # as much as the reordering saves (≈ 40 ms for 71 blocks of 178 × 178).
        block = lambda k: _take(_take(D[k], order, 0), order, 1) + jnp.diag(shift[k][order])  # noqa: E731
        coupling = lambda k: _take(_take(L[k], order, 0), order[n - s :], 1)  # noqa: E731

    def running(carry):
        k, _, _, ok = carry
        return ok & (k < K)

    def step(carry):
        k, Lc, W, _ = carry
        # W_k = L_k Lc_{k−1}^{−T}; with L_k zero but in its last s columns, so is W_k, and
        # those columns need only the trailing s × s block of Lc_{k−1}.
        Wt = solve_triangular(Lc[k - 1][n - s :, n - s :], coupling(k - 1).T, lower=True)  # W_kᵀ (s, n)
        factor = jnp.linalg.cholesky(block(k) - Wt.T @ Wt)
        ok = jnp.all(jnp.isfinite(factor))
        return k + ok, Lc.at[k].set(factor), W.at[k - 1].set(Wt.T), ok

    # The factors are updated in place, indexed, rather than stacked as a scan's outputs
    # (80 ms against 66 ms to factor 71 blocks of 178 × 178 here; 36 ms against 10.5 ms for a
    # solve, where XLA copied blocks between the two scans). The loop stops at the first
    # block that is not positive definite: an inertia correction's failed attempts then cost
    # only the blocks up to it.
    first = jnp.linalg.cholesky(block(0))
    ok = jnp.all(jnp.isfinite(first))
    if K == 1:  # no coupling blocks to index
        return first[None], jnp.zeros((0, n, s), D.dtype), ok.astype(jnp.int32)
    carry = (ok.astype(jnp.int32), jnp.zeros_like(D).at[0].set(first), jnp.zeros((K - 1, n, s), D.dtype), ok)
    factored, Lc, W, _ = jax.lax.while_loop(running, step, carry)
    return Lc, W, factored


def _solve_tridiagonal(Lc, W, R):
    """Solve the tridiagonal part for right-hand sides R (K, n, r) → (K, n, r)."""
    K, n = Lc.shape[:2]
    s = W.shape[-1]

    def forward(k, y):
        return y.at[k].set(solve_triangular(Lc[k], R[k] - W[k - 1] @ y[k - 1][n - s :], lower=True))

    y = jnp.zeros_like(R).at[0].set(solve_triangular(Lc[0], R[0], lower=True))
    if K == 1:  # no coupling blocks to index
        return solve_triangular(Lc[0], y[0], lower=True, trans="T")[None]
    y = jax.lax.fori_loop(1, K, forward, y)

    def backward(i, x):
        k = K - 2 - i
        rhs = y[k].at[n - s :].add(-(W[k].T @ x[k + 1]))
        return x.at[k].set(solve_triangular(Lc[k], rhs, lower=True, trans="T"))

    last = solve_triangular(Lc[-1], y[-1], lower=True, trans="T")
    return jax.lax.fori_loop(0, K - 1, backward, jnp.zeros_like(R).at[-1].set(last))


def coupled_order(n, coupled):
    """Each knot's variable order with the ``coupled`` columns (a sequence of indices in 0..n−1,
    or None: all) last, as a tuple, and the number s of coupled columns."""
    if coupled is None:
        return tuple(range(n)), n
    coupled = np.unique(np.asarray(coupled, dtype=int))
    if coupled.size and (coupled.min() < 0 or coupled.max() >= n):
        raise ValueError(f"coupled columns must lie in 0..{n - 1}, got {coupled.min()}..{coupled.max()}")
    order = np.concatenate([np.setdiff1d(np.arange(n), coupled), coupled])
    return tuple(int(i) for i in order), int(coupled.size)


def _take(x, indices, axis):
    """x indexed by the static ``indices`` along ``axis``, as slices of their contiguous runs
    concatenated: XLA's CPU gather took ≈ 40 ms to reorder 71 blocks of 178 × 178."""
    cuts = np.flatnonzero(np.diff(indices) != 1) + 1
    runs = [(int(r[0]), int(r[-1]) + 1) for r in np.split(indices, cuts) if r.size] or [(0, 0)]
    return jnp.concatenate([jax.lax.slice_in_dim(x, a, b, axis=axis) for a, b in runs], axis=axis)


def factor(D, L, B, C, coupled=None, shift=None, corner_shift=None):
    """Factor the bordered block-tridiagonal SPD matrix.

    D: (K, n, n) diagonal blocks; L: (K − 1, n, n) blocks below the diagonal (block (k+1, k));
    B: (K, n, m) border; C: (m, m). coupled (static, optional): the columns in which every L_k
    can be non-zero (entries of L outside them are ignored: they must be 0). shift (K, n),
    corner_shift (m,) (optional): added to the diagonals of D and C, block by block as they are
    factored (an inertia correction's attempts then share one D). Returns a ``BlockCholesky``.
    """
    D, L, B, C = (jnp.asarray(a) for a in (D, L, B, C))
    n = D.shape[-1]
    shift = jnp.zeros(D.shape[:2], D.dtype) if shift is None else jnp.asarray(shift)
    C = C if corner_shift is None else C + jnp.diag(corner_shift)
    order, s = coupled_order(n, coupled)
    p = None if coupled is None else np.asarray(order)
    if p is not None:
        B = _take(B, p, 1)
    Lc, W, factored = _factor_tridiagonal(D, L, p, s, shift)
    K = D.shape[0]
    # A⁻¹ B only when every block was factored: an inertia correction's failed attempts (1.5 of
    # the 2.5 per iteration on take-off N = 70) then cost no solve.
    X = jax.lax.cond(factored == K, lambda: _solve_tridiagonal(Lc, W, B), lambda: jnp.zeros_like(B))
    schur = jnp.linalg.cholesky(C - jnp.einsum("kna,knb->ab", B, X))
    return BlockCholesky(diagonal=Lc, subdiagonal=W, border_solution=X, schur=schur, border=B,
                         factored=factored, order=None if coupled is None else order)


def solve(chol, r, s):
    """Solve with a ``BlockCholesky``: r (K, n), s (m,) → (x (K, n), y (m,))."""
    r = jnp.asarray(r)
    if chol.order is not None:
        p = np.asarray(chol.order)
        r = _take(r, p, 1)
    x0 = _solve_tridiagonal(chol.diagonal, chol.subdiagonal, r[..., None])[..., 0]
    rhs = s - jnp.einsum("knm,kn->m", chol.border, x0)
    y = jax.scipy.linalg.cho_solve((chol.schur, True), rhs)
    x = x0 - jnp.einsum("knm,m->kn", chol.border_solution, y)
    if chol.order is not None:
        x = _take(x, np.argsort(p), 1)
    return x, y


def matvec(D, L, B, C, x, y):
    """Product of the bordered block-tridiagonal symmetric matrix with (x (K, n), y (m,))."""
    top = jnp.einsum("kab,kb->ka", D, x) + jnp.einsum("kab,b->ka", B, y)
    top = top.at[1:].add(jnp.einsum("kab,kb->ka", L, x[:-1]))
    top = top.at[:-1].add(jnp.einsum("kba,kb->ka", L, x[1:]))
    return top, jnp.einsum("kab,ka->b", B, x) + C @ y
