"""Block-tridiagonal symmetric positive-definite systems with a dense border.

    [ D_0   L_1ᵀ                 B_0     ] [x_0]   [r_0]
    [ L_1   D_1   L_2ᵀ           B_1     ] [x_1]   [r_1]
    [       ⋱     ⋱     ⋱        ⋮       ] [ ⋮ ] = [ ⋮ ]
    [             L_{K−1} D_{K−1} B_{K−1} ] [   ]   [   ]
    [ B_0ᵀ  B_1ᵀ   …     B_{K−1}ᵀ C       ] [y  ]   [s  ]

The block Cholesky factorisation runs forward in ``jax.lax.scan`` (a Riccati-like recursion,
O(K n³)); the border (the global variables) is eliminated by a Schur complement. No dense
factorisation of the whole matrix is ever formed. A matrix that is not positive definite
gives a factor with non-finite entries: ``BlockCholesky.ok`` reports it.
"""

import dataclasses

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BlockCholesky:
    """A = 𝓛 𝓛ᵀ with 𝓛 block lower-bidiagonal: diagonal (K, n, n), sub-diagonal (K − 1, n, n);
    plus the border's Schur complement factor (m, m) and A⁻¹B (K, n, m)."""

    diagonal: jax.Array
    subdiagonal: jax.Array
    border_solution: jax.Array
    schur: jax.Array
    border: jax.Array

    @property
    def ok(self):
        """True when every factor is finite (the matrix was positive definite)."""
        return jnp.all(jnp.isfinite(self.diagonal)) & jnp.all(jnp.isfinite(self.schur))


def _factor_tridiagonal(D, L):
    """Block Cholesky of the tridiagonal part: returns (Lc (K, n, n), W (K − 1, n, n))."""
    first = jnp.linalg.cholesky(D[0])

    def step(previous, blocks):
        D_k, L_k = blocks
        # W_k = L_k Lc_{k−1}^{−T}
        W = solve_triangular(previous, L_k.T, lower=True).T
        factor = jnp.linalg.cholesky(D_k - W @ W.T)
        return factor, (factor, W)

    _, (rest, W) = jax.lax.scan(step, first, (D[1:], L))
    return jnp.concatenate([first[None], rest]), W


def _solve_tridiagonal(Lc, W, R):
    """Solve the tridiagonal part for right-hand sides R (K, n, r) → (K, n, r)."""
    y0 = solve_triangular(Lc[0], R[0], lower=True)

    def forward(previous, blocks):
        Lc_k, W_k, R_k = blocks
        y = solve_triangular(Lc_k, R_k - W_k @ previous, lower=True)
        return y, y

    _, ys = jax.lax.scan(forward, y0, (Lc[1:], W, R[1:]))
    y = jnp.concatenate([y0[None], ys])
    x_last = solve_triangular(Lc[-1], y[-1], lower=True, trans="T")

    def backward(following, blocks):
        Lc_k, W_next, y_k = blocks
        x = solve_triangular(Lc_k, y_k - W_next.T @ following, lower=True, trans="T")
        return x, x

    _, xs = jax.lax.scan(backward, x_last, (Lc[:-1], W, y[:-1]), reverse=True)
    return jnp.concatenate([xs, x_last[None]])


def factor(D, L, B, C):
    """Factor the bordered block-tridiagonal SPD matrix.

    D: (K, n, n) diagonal blocks; L: (K − 1, n, n) blocks below the diagonal (block (k+1, k));
    B: (K, n, m) border; C: (m, m). Returns a ``BlockCholesky``.
    """
    Lc, W = _factor_tridiagonal(D, L)
    X = _solve_tridiagonal(Lc, W, B)  # A⁻¹ B
    schur = jnp.linalg.cholesky(C - jnp.einsum("kna,knb->ab", B, X))
    return BlockCholesky(diagonal=Lc, subdiagonal=W, border_solution=X, schur=schur, border=B)


def solve(chol, r, s):
    """Solve with a ``BlockCholesky``: r (K, n), s (m,) → (x (K, n), y (m,))."""
    x0 = _solve_tridiagonal(chol.diagonal, chol.subdiagonal, r[..., None])[..., 0]
    rhs = s - jnp.einsum("knm,kn->m", chol.border, x0)
    y = jax.scipy.linalg.cho_solve((chol.schur, True), rhs)
    return x0 - jnp.einsum("knm,m->kn", chol.border_solution, y), y


def matvec(D, L, B, C, x, y):
    """Product of the bordered block-tridiagonal symmetric matrix with (x (K, n), y (m,))."""
    top = jnp.einsum("kab,kb->ka", D, x) + jnp.einsum("kab,b->ka", B, y)
    top = top.at[1:].add(jnp.einsum("kab,kb->ka", L, x[:-1]))
    top = top.at[:-1].add(jnp.einsum("kba,kb->ka", L, x[1:]))
    return top, jnp.einsum("kab,ka->b", B, x) + C @ y
