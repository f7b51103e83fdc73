"""Block-tridiagonal symmetric positive-definite systems with a dense border.

    [ D_0   L_1ᵀ                 B_0     ] [x_0]   [r_0]
    [ L_1   D_1   L_2ᵀ           B_1     ] [x_1]   [r_1]
    [       ⋱     ⋱     ⋱        ⋮       ] [ ⋮ ] = [ ⋮ ]
    [             L_{K−1} D_{K−1} B_{K−1} ] [   ]   [   ]
    [ B_0ᵀ  B_1ᵀ   …     B_{K−1}ᵀ C       ] [y  ]   [s  ]

The block Cholesky factorisation runs from both ends, a chain from the last block and then one
from the first (Riccati-like recursions, O(K n³), each a ``jax.lax.while_loop``), and meets in
the middle block; the border (the global variables) is eliminated by a Schur complement. No
dense factorisation of the whole matrix is ever formed. A matrix that is not positive definite
stops the factorisation at the first failing block: ``BlockCholesky.ok`` reports it. Whether a
matrix is positive definite does not depend on the order of elimination, but where it fails
does: an interior-point method's Newton matrices on a trajectory are indefinite mostly in the
blocks of the last knots, which the backward chain meets first, without the forward chain's
work.

When the coupling blocks L_k are non-zero only in some columns (``coupled``: of a stage-wise
NLP, the variables of knot k that its transition rows touch), each knot's variables are
ordered with those columns last: the Schur updates then involve only them (forward: a
triangular solve with n right-hand sides on the trailing s × s factor and an (n × s)(s × n)
product; backward: a triangular solve with s right-hand sides and an (s × n)(n × s) product
into the trailing s × s block; instead of n × n ones).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular


def _one_by_one_on_cpu(fn):
    """``fn`` (LAPACK-backed, of arrays) whose ``vmap`` runs the instances one after another
    (``lax.map``) on a CPU, and as one batched kernel elsewhere. jaxlib's batched CPU LAPACK
    kernels split their batch over the intra-op thread pool and block a pool thread until the
    pieces are done: under a vmapped solve the two chains of the two-ended factorisation run
    two such kernels at once and, on a two-thread pool, each waits forever for work queued behind
    the other (seen: both threads in ``lapack_dpotrf_ffi``'s ``ParallelBatchMap``)."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        args = tuple(a if batched else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, batched in zip(args, in_batched))
        if jax.default_backend() == "cpu":
            return jax.lax.map(lambda xs: wrapped(*xs), args), True
        return jax.vmap(fn)(*args), True

    return wrapped


cholesky = _one_by_one_on_cpu(jnp.linalg.cholesky)
lower_solve = _one_by_one_on_cpu(lambda a, b: solve_triangular(a, b, lower=True))
lower_transposed_solve = _one_by_one_on_cpu(lambda a, b: solve_triangular(a, b, lower=True, trans="T"))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Chain:
    """One chain of a two-ended block Cholesky factorisation (``factor``), M slots: the factors of
    its diagonal blocks in the order it factored them, transposed (upper triangular), blocks
    (M, n, n), and the trailing s columns of their couplings to the next block of the chain,
    couplings (M, n, s). Transposed because LAPACK, which factors and solves, keeps matrices
    column by column: a row-major Lᵀ is a column-major L, read without a transposing copy (one
    per block and solve)."""

    blocks: jax.Array
    couplings: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BlockCholesky:
    """A = 𝓛 𝓛ᵀ, each knot's variables in the order ``order`` (static; the coupled columns last),
    with 𝓛 block lower-bidiagonal above the middle block M = K // 2 and upper-bidiagonal below
    it: the forward chain (blocks 0, 1, …, M − 1), the middle block's factor (n, n), the
    backward chain (blocks K − 1, K − 2, …, M + 1: K − 1 − M of its slots used); plus the
    border's Schur complement factor (m, m), A⁻¹B (K, n, m), and the number of diagonal blocks
    factored (K unless a block was not positive definite: the factorisation stops at the first)."""

    forward: Chain
    middle: jax.Array
    backward: Chain
    border_solution: jax.Array
    schur: jax.Array
    border: jax.Array
    factored: jax.Array
    order: tuple = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def ok(self):
        """True when every block was factored and every factor is finite (the matrix was
        positive definite)."""
        return (self.factored == self.border_solution.shape[-3]) & jnp.all(jnp.isfinite(self.schur))

    @property
    def diagonal(self):
        """The factors of the diagonal blocks in knot order, (K, n, n) (a copy, for inspection)."""
        K = self.border_solution.shape[-3]
        chains = jnp.concatenate([self.forward.blocks, _stored(self.middle)[None], self.backward.blocks[: K - 1 - K // 2][::-1]])
        return jnp.swapaxes(chains, -1, -2)


def _factor_tridiagonal(D, L, order, s, shift, free=None, buffers=None):
    """Two-ended block Cholesky of the tridiagonal part, D's diagonals plus ``shift`` (K, n), with
    each knot's variables in the order ``order`` (static (n,) indices; None: as given; ``shift``
    and ``free`` already in that order), L's columns non-zero only in the last s of that order
    (``coupled_order``). free (K, n) (optional): 0 on the variables held fixed, whose rows and
    columns are replaced by the identity's block by block (``factor``). buffers (optional): the
    (forward, backward) ``Chain`` of an earlier factorisation of the same shapes, whose arrays
    hold the new factors: every slot the solve reads is written again, and no zeros are filled.

    Above the middle block M = K // 2, 𝓛[k, k] = Lc_k and 𝓛[k+1, k] = L_k Lc_k^{−T}, non-zero
    in its last s columns (the forward chain's couplings, (n, s)); below it 𝓛[k, k] = Lc_k and
    𝓛[k−1, k] = (Lc_k^{−1} L_{k−1})ᵀ, non-zero in its last s rows (the backward chain's
    couplings: Lc_k^{−1} L_{k−1}'s last s columns); at M, Lc_M Lc_Mᵀ is what both chains leave
    of the block. The backward chain runs first, then the forward one; each stops at the first
    block that is not positive definite: an inertia correction's failed attempts, indefinite
    mostly in the last knots' blocks, then cost a few blocks.

    Returns (forward ``Chain``, the middle factor (n, n), backward ``Chain``, the number of
    diagonal blocks factored: K when A is positive definite)."""
    K, n = D.shape[:2]
    M, back = K // 2, K - 1 - K // 2  # forward chain 0..M−1, backward chain K−1..M+1: M or M − 1 blocks
    if order is None:
        stored_block, stored_coupling = (lambda k: D[k]), (lambda k: L[k][:, n - s :])
    else:
        # Reordered block by block, in cache: reordering the (K, n, n) arrays up front cost
        # as much as the reordering saves.
        stored_block = lambda k: _take(_take(D[k], order, 0), order, 1)  # noqa: E731
        stored_coupling = lambda k: _take(_take(L[k], order, 0), order[n - s :], 1)  # noqa: E731
    if free is None:
        block = lambda k: stored_block(k) + jnp.diag(shift[k])  # noqa: E731
        coupling = stored_coupling
    else:
        # Masked block by block, in cache: masking the (K, n, n) arrays up front was a pass over
        # them of its own (≈ 7 ms a take-off iteration).
        block = lambda k: (free[k][:, None] * stored_block(k) * free[k][None, :]  # noqa: E731
                           + jnp.diag(free[k] * shift[k] + 1 - free[k]))
        coupling = lambda k: free[k + 1][:, None] * stored_coupling(k) * free[k][None, n - s :]  # noqa: E731

    def below(previous, k):
        """(L_{k−1} Lc_{k−1}^{−T})ᵀ's non-zero rows (s, n), for block k of the forward chain (previous:
        Lc_{k−1} as the chain stores it): they need only the trailing s × s block of Lc_{k−1}."""
        return lower_solve(previous[n - s :, n - s :].T, coupling(k - 1).T)

    def above(following, k):
        """Lc_{k+1}^{−1} L_k's non-zero columns (n, s), for block k of the backward chain
        (following: Lc_{k+1} as the chain stores it): their Gram product touches only the last s rows and columns of block k."""
        return lower_solve(following.T, coupling(k))

    def minus_above(A, Y):
        return A.at[n - s :, n - s :].add(-(Y.T @ Y))

    def positive(factor):
        # A failed factor is NaN on its diagonal, and a non-finite entry of the lower triangle
        # reaches the diagonal below it: the diagonal alone, not a pass over the block.
        return jnp.all(jnp.isfinite(jnp.diagonal(factor)))

    def step_backward(carry):
        j, Lb, Wb, count, _ = carry
        Y = above(Lb[j - 1], K - 1 - j)
        factor = cholesky(minus_above(block(K - 1 - j), Y))
        ok = positive(factor)
        return j + 1, Lb.at[j].set(_stored(factor)), Wb.at[j - 1].set(Y), count + ok, ok

    def step_forward(carry):
        j, Lf, Wf, count, _ = carry
        Wt = below(Lf[j - 1], j)
        factor = cholesky(block(j) - Wt.T @ Wt)
        ok = positive(factor)
        return j + 1, Lf.at[j].set(_stored(factor)), Wf.at[j - 1].set(Wt.T), count + ok, ok

    def running(steps):
        return lambda carry: carry[-1] & (carry[0] < steps)

    # The backward chain first, then the forward one, each stopping at its first indefinite
    # block: an interior-point method's Newton matrices on a trajectory are indefinite mostly
    # in the last knots' blocks (take-off N = 70: 97 % of the failed attempts in knots 44–70), found
    # here without the forward chain's work. Each chain in arrays of its own, updated in place,
    # indexed: with both chains' blocks in one array XLA copied the whole array at every step (a
    # factorisation 3.6× slower), and a scan's stacked outputs factor 1.2× and solve 3.4× slower.
    if buffers is None:
        Lf, Lb = jnp.zeros((M, n, n), D.dtype), jnp.zeros((M, n, n), D.dtype)
        Wf, Wb = jnp.zeros((M, n, s), D.dtype), jnp.zeros((M, n, s), D.dtype)
    else:
        (Lf, Wf), (Lb, Wb) = ((c.blocks, c.couplings) for c in buffers)
    count, ok = jnp.asarray(0), jnp.asarray(True)
    if back >= 1:
        last = cholesky(block(K - 1))
        Lb, count, ok = Lb.at[0].set(_stored(last)), count + positive(last), positive(last)
    if back >= 2:
        _, Lb, Wb, count, ok = jax.lax.while_loop(running(back), step_backward, (jnp.asarray(1), Lb, Wb, count, ok))
    if M >= 1:
        first = cholesky(block(0))
        Lf, count, ok = Lf.at[0].set(_stored(first)), count + (ok & positive(first)), ok & positive(first)
    if M >= 2:
        _, Lf, Wf, count, ok = jax.lax.while_loop(running(M), step_forward, (jnp.asarray(1), Lf, Wf, count, ok))
    # The middle block, computed whatever the chains found (one block; a branch would copy them).
    A = block(M)
    if M >= 1:
        Wt = below(Lf[M - 1], M)
        A, Wf = A - Wt.T @ Wt, Wf.at[M - 1].set(Wt.T)
    if back >= 1:
        Y = above(Lb[back - 1], M)
        A, Wb = minus_above(A, Y), Wb.at[back - 1].set(Y)
    middle = cholesky(A)
    return Chain(Lf, Wf), middle, Chain(Lb, Wb), count + (ok & positive(middle))


def _solve_tridiagonal(forward, middle, backward, R):
    """Solve the tridiagonal part for right-hand sides R (K, n, r) → (K, n, r), with the factors
    of ``_factor_tridiagonal``: 𝓛 y = R from both ends to the middle block, then 𝓛ᵀ x = y from
    the middle outwards."""
    K, n = R.shape[:2]
    M, back = K // 2, K - 1 - K // 2
    s = forward.couplings.shape[-1]
    Lf, Wf, Lb, Wb = forward.blocks, forward.couplings, backward.blocks, backward.couplings

    def lower(stored, rhs):
        return lower_solve(stored.T, rhs)

    def upper(stored, rhs):
        return lower_transposed_solve(stored.T, rhs)

    def inward(j, carry):
        yf, yb = carry
        yf = yf.at[j].set(lower(Lf[j], R[j] - Wf[j - 1] @ yf[j - 1][n - s :]))
        yb = yb.at[j].set(lower(Lb[j], R[K - 1 - j].at[n - s :].add(-(Wb[j - 1].T @ yb[j - 1]))))
        return yf, yb

    yf, yb = jnp.zeros((M,) + R.shape[1:], R.dtype), jnp.zeros((M,) + R.shape[1:], R.dtype)
    rhs = R[M]
    if M >= 1:
        yf = yf.at[0].set(lower(Lf[0], R[0]))
    if back >= 1:
        yb = yb.at[0].set(lower(Lb[0], R[K - 1]))
    if M >= 2:  # K even: the backward chain's last slot gets a value no one reads
        yf, yb = jax.lax.fori_loop(1, M, inward, (yf, yb))
    if M >= 1:
        rhs = rhs - Wf[M - 1] @ yf[M - 1][n - s :]
    if back >= 1:
        rhs = rhs.at[n - s :].add(-(Wb[back - 1].T @ yb[back - 1]))
    x_middle = upper(_stored(middle), lower(_stored(middle), rhs))

    def outward(i, carry):
        xf, xb, previous_f, previous_b = carry
        k, b = M - 1 - i, back - 1 - i  # the forward chain's block k, the backward chain's slot b
        new_f = upper(Lf[k], yf[k].at[n - s :].add(-(Wf[k].T @ previous_f)))
        new_b = upper(Lb[b], yb[b] - Wb[b] @ previous_b[n - s :])
        # K even: b = −1 at the last step, a spare slot's value no one reads.
        return xf.at[k].set(new_f), xb.at[b].set(new_b), new_f, jnp.where(b >= 0, new_b, previous_b)

    xf, xb = jnp.zeros_like(yf), jnp.zeros_like(yb)
    if M >= 1:
        xf, xb, _, _ = jax.lax.fori_loop(0, M, outward, (xf, xb, x_middle, x_middle))
    return jnp.concatenate([xf, x_middle[None], xb[:back][::-1]])


def _stored(factor):
    """A lower triangular factor as a chain stores it: transposed (``Chain``)."""
    return jnp.swapaxes(factor, -1, -2)


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
    concatenated: XLA's CPU gather is far slower at reordering the blocks."""
    cuts = np.flatnonzero(np.diff(indices) != 1) + 1
    runs = [(int(r[0]), int(r[-1]) + 1) for r in np.split(indices, cuts) if r.size] or [(0, 0)]
    return jnp.concatenate([jax.lax.slice_in_dim(x, a, b, axis=axis) for a, b in runs], axis=axis)


def factor(D, L, B, C, coupled=None, shift=None, corner_shift=None, free=None, into=None):
    """Factor the bordered block-tridiagonal SPD matrix.

    D: (K, n, n) diagonal blocks; L: (K − 1, n, n) blocks below the diagonal (block (k+1, k));
    B: (K, n, m) border; C: (m, m). coupled (static, optional): the columns in which every L_k
    can be non-zero (entries of L outside them are ignored: they must be 0). shift (K, n),
    corner_shift (m,) (optional): added to the diagonals of D and C, block by block as they are
    factored (an inertia correction's attempts then share one D). free (optional): a pair
    ((K, n), (m,)) of 0/1 masks, 0 on the variables held fixed: their rows and columns (of D, L, B
    and C) are replaced by the identity's and their shifts ignored, so that ``solve`` returns
    the right-hand side there. into (optional): a ``BlockCholesky`` of the same shapes whose
    storage the new factor reuses (an inertia correction's earlier attempt: no zeros filled per
    attempt). Returns a ``BlockCholesky``.
    """
    D, L, B, C = (jnp.asarray(a) for a in (D, L, B, C))
    n = D.shape[-1]
    shift = jnp.zeros(D.shape[:2], D.dtype) if shift is None else jnp.asarray(shift)
    corner_shift = jnp.zeros(C.shape[:1], C.dtype) if corner_shift is None else jnp.asarray(corner_shift)
    if free is not None:
        fz, ft = (jnp.asarray(f, D.dtype) for f in free)
        B = fz[:, :, None] * B * ft
        C = ft[:, None] * C * ft[None, :] + jnp.diag(1 - ft)
        corner_shift = ft * corner_shift
    C = C + jnp.diag(corner_shift)
    order, s = coupled_order(n, coupled)
    # Coupled columns already last: nothing to reorder (the same run time, half the compilation).
    order = None if order == tuple(range(n)) else order
    p = None if order is None else np.asarray(order)
    if p is not None:
        B, shift = _take(B, p, 1), _take(shift, p, 1)
        fz = None if free is None else _take(fz, p, 1)
    buffers = None if into is None else (into.forward, into.backward)
    forward, middle, backward, factored = _factor_tridiagonal(D, L, p, s, shift, None if free is None else fz, buffers)
    K = D.shape[0]
    # A⁻¹ B only when every block was factored: an inertia correction's failed attempts (1.5 of
    # the 2.5 per iteration on take-off N = 70) then cost no solve.
    X = jax.lax.cond(factored == K, lambda: _solve_tridiagonal(forward, middle, backward, B), lambda: jnp.zeros_like(B))
    schur = cholesky(C - jnp.einsum("kna,knb->ab", B, X))
    return BlockCholesky(forward=forward, middle=middle, backward=backward, border_solution=X, schur=schur, border=B,
                         factored=factored, order=order)


def solve(chol, r, s):
    """Solve with a ``BlockCholesky``: r (K, n), s (m,) → (x (K, n), y (m,))."""
    r = jnp.asarray(r)
    if chol.order is not None:
        p = np.asarray(chol.order)
        r = _take(r, p, 1)
    x0 = _solve_tridiagonal(chol.forward, chol.middle, chol.backward, r[..., None])[..., 0]
    rhs = s - jnp.einsum("knm,kn->m", chol.border, x0)
    y = jax.scipy.linalg.cho_solve((chol.schur, True), rhs)
    x = x0 - jnp.einsum("knm,m->kn", chol.border_solution, y)
    if chol.order is not None:
        x = _take(x, np.argsort(p), 1)
    return x, y


def matvec(D, L, B, C, x, y):
    """Product of the bordered block-tridiagonal symmetric matrix with (x (K, n), y (m,)). L: the
    (K − 1, n, n) blocks, or an operator on them with ``below(x)`` = (L_k x_k)_k and
    ``above(x)`` = (L_kᵀ x_{k+1})_k, each (K − 1, n) (``stagewise.Coupling``)."""
    top = jnp.einsum("kab,kb->ka", D, x) + jnp.einsum("kab,b->ka", B, y)
    if hasattr(L, "below"):
        below, above = L.below(x), L.above(x)
    else:
        below, above = jnp.einsum("kab,kb->ka", L, x[:-1]), jnp.einsum("kba,kb->ka", L, x[1:])
    top = top.at[1:].add(below).at[:-1].add(above)
    return top, jnp.einsum("kab,ka->b", B, x) + C @ y
