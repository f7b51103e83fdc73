"""The bordered block-tridiagonal solver against a dense solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import linalg


def random_system(K, n, m, seed):
    """A random SPD bordered block-tridiagonal matrix, as blocks and as a dense matrix."""
    rng = np.random.default_rng(seed)
    N = K * n + m
    # Build from a random block-bidiagonal factor so the result is SPD with the right pattern.
    F = np.zeros((N, N))
    for k in range(K):
        F[k * n : (k + 1) * n, k * n : (k + 1) * n] = 0.3 * np.tril(rng.normal(size=(n, n))) + 2 * np.eye(n)
        if k:
            F[k * n : (k + 1) * n, (k - 1) * n : k * n] = 0.3 * rng.normal(size=(n, n))
    F[K * n :, :] = 0.3 * rng.normal(size=(m, N))
    F[K * n :, K * n :] = np.tril(F[K * n :, K * n :]) + 3 * np.eye(m)
    F[: K * n, K * n :] = 0
    A = F @ F.T
    D = np.stack([A[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(K)])
    L = np.zeros((K - 1, n, n))
    for k in range(K - 1):
        L[k] = A[(k + 1) * n : (k + 2) * n, k * n : (k + 1) * n]
    B = np.stack([A[k * n : (k + 1) * n, K * n :] for k in range(K)])
    C = A[K * n :, K * n :]
    return A, D, L, B, C


def coupled_only(A, L, coupled):
    """(A, L) with the coupling blocks L zeroed outside the ``coupled`` columns (None: all kept),
    in the blocks and in the dense matrix A alike (copies)."""
    if coupled is None:
        return A, L
    K, n = L.shape[0] + 1, L.shape[-1]
    A, L = A.copy(), L.copy()
    L[:, :, np.setdiff1d(np.arange(n), coupled)] = 0.0
    for k in range(K - 1):
        A[(k + 1) * n : (k + 2) * n, k * n : (k + 1) * n] = L[k]
        A[k * n : (k + 1) * n, (k + 1) * n : (k + 2) * n] = L[k].T
    return A, L


@pytest.mark.parametrize("K, n, m", [(1, 3, 1), (2, 3, 1), (3, 2, 1), (7, 5, 2), (8, 4, 2), (20, 12, 1), (5, 4, 0)])
def test_solve_matches_dense(K, n, m):
    A, D, L, B, C = random_system(K, n, m, seed=K * 100 + n)
    rng = np.random.default_rng(0)
    r, s = rng.normal(size=(K, n)), rng.normal(size=m)
    chol = jax.jit(linalg.factor)(D, L, B.reshape(K, n, m), C.reshape(m, m))
    x, y = jax.jit(linalg.solve)(chol, r, s)
    expected = np.linalg.solve(A, np.concatenate([r.reshape(-1), s]))
    assert bool(chol.ok)
    assert np.allclose(np.concatenate([np.asarray(x).reshape(-1), y]), expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("indefinite, factored, untouched", [(7, 1, [1, 2, 3, 5, 6]), (1, 5, [2, 3])])
def test_not_positive_definite_is_reported_where_either_chain_meets_it(indefinite, factored, untouched):
    """The factorisation runs the backward chain (blocks 8, 7, 6, 5 of 9) and then the forward
    chain (0, 1, 2, 3), meeting at block 4, and stops at the first indefinite block: block 7
    after block 8 alone, block 1 after the backward chain and block 0; the blocks after it are
    never factored."""
    A, D, L, B, C = random_system(9, 3, 1, seed=1)
    D = D.copy()
    D[indefinite] -= 1e3 * np.eye(3)
    chol = linalg.factor(D, L, B, C)
    assert not bool(chol.ok)
    assert int(chol.factored) == factored
    assert np.all(np.asarray(chol.diagonal)[untouched] == 0.0)


def test_a_failing_last_block_middle_block_or_schur_complement_is_reported():
    A, D, L, B, C = random_system(4, 3, 1, seed=2)
    last = D.copy()
    last[3] -= 1e3 * np.eye(3)
    chol = linalg.factor(last, L, B, C)
    assert not bool(chol.ok) and int(chol.factored) == 0  # the backward chain's first block: found at once
    middle = D.copy()
    middle[2] -= 1e3 * np.eye(3)
    chol = linalg.factor(middle, L, B, C)
    assert not bool(chol.ok) and int(chol.factored) == 3  # blocks 0, 1 and 3 factored, 2 (the middle) not
    chol = linalg.factor(D, L, B, C - 1e3)
    assert int(chol.factored) == 4 and not bool(chol.ok)
    assert bool(linalg.factor(D, L, B, C).ok)


def test_vmap_over_systems():
    systems = [random_system(6, 4, 1, seed=s) for s in range(3)]
    D, L, B, C = (jnp.stack([sys[i] for sys in systems]) for i in range(1, 5))
    r = jnp.ones((3, 6, 4))
    s = jnp.ones((3, 1))
    x, y = jax.vmap(lambda D, L, B, C, r, s: linalg.solve(linalg.factor(D, L, B, C), r, s))(D, L, B, C, r, s)
    for i, (A, *_rest) in enumerate(systems):
        expected = np.linalg.solve(A, np.ones(25))
        assert np.allclose(np.concatenate([np.asarray(x[i]).reshape(-1), y[i]]), expected, atol=1e-9)


def test_matvec_matches_dense():
    A, D, L, B, C = random_system(6, 4, 2, seed=3)
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(6, 4)), rng.normal(size=2)
    top, bottom = linalg.matvec(D, L, B, C, x, y)
    expected = A @ np.concatenate([x.reshape(-1), y])
    assert np.abs(np.concatenate([np.asarray(top).reshape(-1), bottom]) - expected).max() <= 1e-12


@pytest.mark.parametrize("K, n, m, coupled", [(7, 6, 2, (4, 1, 5)), (8, 6, 1, (4, 1, 5)), (3, 5, 1, ()), (4, 4, 1, (0, 1, 2, 3)),
                                              (2, 3, 1, (2,)), (1, 3, 1, (2,)), (7, 6, 2, (3, 4, 5)), (8, 6, 1, (5,))])
def test_coupling_in_some_columns(K, n, m, coupled):
    """Coupling blocks non-zero only in the declared columns: the same solution as a dense solve,
    and a wrong declaration (a non-zero column left out) is not silently the same; the columns
    anywhere (the blocks reordered) or already last (nothing reordered)."""
    A, D, L, B, C = random_system(K, n, m, seed=K + n)
    A, L = coupled_only(A, L, coupled)
    A[: K * n, : K * n] += 50 * np.eye(K * n)  # still SPD with the zeroed blocks (diagonally dominant)
    D = D + 50 * np.eye(n)
    rng = np.random.default_rng(1)
    r, s = rng.normal(size=(K, n)), rng.normal(size=m)
    chol = jax.jit(linalg.factor, static_argnums=4)(D, L, B, C, coupled)
    x, y = jax.jit(linalg.solve)(chol, r, s)
    expected = np.linalg.solve(A, np.concatenate([r.reshape(-1), s]))
    assert bool(chol.ok) and chol.forward.couplings.shape[-1] == len(coupled)
    assert np.allclose(np.concatenate([np.asarray(x).reshape(-1), y]), expected, rtol=1e-10, atol=1e-10)
    if K > 1 and len(coupled) < n:
        x_wrong, _ = linalg.solve(linalg.factor(D, L + 0.5, B, C, coupled), r, s)
        x_right, _ = linalg.solve(linalg.factor(D, L + 0.5, B, C), r, s)
        assert np.abs(np.asarray(x_wrong) - np.asarray(x_right)).max() > 1e-6


def test_coupled_columns_out_of_range_are_refused():
    A, D, L, B, C = random_system(3, 4, 1, seed=5)
    with pytest.raises(ValueError, match="coupled columns"):
        linalg.factor(D, L, B, C, coupled=(1, 4))


@pytest.mark.parametrize("coupled", [None, (4, 1, 5), (3, 4, 5)])
def test_diagonal_shifts_added_as_factored(coupled):
    """factor(D, …, shift=s, corner_shift=c) is factor(D + diag s, …, C + diag c) to the last bit,
    with or without the coupled-columns reordering, and a shift that makes a block indefinite is
    reported as such."""
    K, n, m = 6, 6, 2
    A, D, L, B, C = random_system(K, n, m, seed=11)
    _, L = coupled_only(A, L, coupled)
    rng = np.random.default_rng(3)
    shift, corner = rng.uniform(0.1, 2.0, size=(K, n)), rng.uniform(0.1, 2.0, size=m)
    shifted = linalg.factor(D, L, B, C, coupled=coupled, shift=shift, corner_shift=corner)
    added = linalg.factor(D + np.stack([np.diag(v) for v in shift]), L, B, C + np.diag(corner), coupled=coupled)
    for a, b in zip(jax.tree.leaves(shifted), jax.tree.leaves(added)):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    negative = shift.copy()
    negative[3] -= 1e3  # block 3 of 6 is where the two chains meet, factored last
    assert int(linalg.factor(D, L, B, C, coupled=coupled, shift=negative).factored) == 5


def test_diagonal_gives_the_lower_triangular_factors():
    """``BlockCholesky.diagonal`` returns the blocks' lower triangular factors: the chains' first
    blocks, knot 0 and knot K − 1, are factored before any update, so their factors are those of
    D_0 and D_{K−1} themselves."""
    K, n, m = 5, 4, 1
    _, D, L, B, C = random_system(K, n, m, seed=21)
    factors = np.asarray(linalg.factor(D, L, B, C).diagonal)
    assert np.all(np.triu(factors, 1) == 0.0)
    for k in (0, K - 1):
        assert np.allclose(factors[k] @ factors[k].T, D[k], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("coupled", [None, (4, 1, 5), (3, 4, 5)])
@pytest.mark.parametrize("fixed_global", [False, True])
def test_fixed_variables_are_held_out(coupled, fixed_global):
    """factor(…, free=(fz, ft)) factors the matrix whose fixed variables' rows and columns are the
    identity's (their shifts ignored): the solve returns the right-hand side there and, on the
    others, the dense solve of the free variables' system with the fixed ones' columns moved to
    the right-hand side as zeros."""
    K, n, m = 7, 6, 2
    A, D, L, B, C = random_system(K, n, m, seed=31)
    A, L = coupled_only(A, L, coupled)
    rng = np.random.default_rng(4)
    fz = (rng.uniform(size=(K, n)) > 0.3).astype(float)
    fz[0, :] = 0.0  # a whole knot fixed, as boundary conditions fix one
    ft = np.ones(m)
    if fixed_global:
        ft[1] = 0.0
    shift, corner = rng.uniform(0.1, 2.0, size=(K, n)), rng.uniform(0.1, 2.0, size=m)
    chol = linalg.factor(D, L, B, C, coupled=coupled, shift=shift, corner_shift=corner, free=(fz, ft))
    r, s = rng.normal(size=(K, n)), rng.normal(size=m)
    x, y = linalg.solve(chol, r, s)
    free = np.concatenate([fz.reshape(-1), ft]) > 0
    dense = A + np.diag(np.concatenate([shift.reshape(-1), corner]))
    rhs = np.concatenate([r.reshape(-1), s])
    expected = rhs.copy()
    expected[free] = np.linalg.solve(dense[np.ix_(free, free)], rhs[free])
    assert bool(chol.ok)
    assert np.allclose(np.concatenate([np.asarray(x).reshape(-1), y]), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("K", [7, 8])
@pytest.mark.parametrize("coupled", [None, (4, 1, 5)])
def test_storage_of_an_earlier_factor_is_reused_exactly(K, coupled):
    """factor(…, into=earlier) in the storage of an earlier factor, one that failed part-way (NaN
    in a chain) or one of another matrix: bit for bit the factor and the solution of a fresh
    factorisation, with K odd and K even (the backward chain's spare slot)."""
    n, m = 6, 1
    A, D, L, B, C = random_system(K, n, m, seed=41)
    A2, D2, L2, B2, C2 = random_system(K, n, m, seed=42)
    _, L = coupled_only(A, L, coupled)
    _, L2 = coupled_only(A2, L2, coupled)
    failed_D = D2.copy()
    failed_D[K // 2 + 1] -= 1e3 * np.eye(n)  # the backward chain's last block: its other blocks factored
    failed = linalg.factor(failed_D, L2, B2, C2, coupled=coupled)
    assert not bool(failed.ok) and not np.all(np.isfinite(np.asarray(failed.backward.blocks)))
    fresh = linalg.factor(D, L, B, C, coupled=coupled)
    r, s = np.random.default_rng(5).normal(size=(K, n)), np.ones(m)
    for earlier in (failed, linalg.factor(D2, L2, B2, C2, coupled=coupled)):
        reused = jax.jit(lambda *a: linalg.factor(*a, coupled=coupled, into=earlier))(D, L, B, C)
        assert bool(reused.ok)
        assert np.array_equal(np.asarray(reused.diagonal), np.asarray(fresh.diagonal))
        for a, b in zip(linalg.solve(reused, r, s), linalg.solve(fresh, r, s)):
            assert np.array_equal(np.asarray(a), np.asarray(b))
