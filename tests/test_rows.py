"""Stage-wise constraint rows (``solver.rows``) against the dense Jacobian they stand for."""

import types

import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import rows
from jaxmm.stagewise import RowSupport


def random_rows(K, n, ng, m, transition, seed):
    """Random path (R = K) or transition (R = K − 1) rows and their dense Jacobian (R m, K n + ng)."""
    rng = np.random.default_rng(seed)
    R = K - 1 if transition else K
    jz, jt = rng.normal(size=(R, m, n)), rng.normal(size=(R, m, ng))
    jn = rng.normal(size=(R, m, n)) if transition else None
    dense = np.zeros((R * m, K * n + ng))
    for k in range(R):
        block = slice(k * m, (k + 1) * m)
        dense[block, k * n : (k + 1) * n] = jz[k]
        if transition:
            dense[block, (k + 1) * n : (k + 2) * n] = jn[k]
        dense[block, K * n :] = jt[k]
    return rows.Rows(jz, jt, jn), dense


def dense_blocks(blocks, K, n):
    D, L, B, C = (np.asarray(b) for b in blocks)
    A = np.zeros((K * n + C.shape[0],) * 2)
    for k in range(K):
        A[k * n : (k + 1) * n, k * n : (k + 1) * n] = D[k]
        A[k * n : (k + 1) * n, K * n :] = B[k]
        A[K * n :, k * n : (k + 1) * n] = B[k].T
        if k:
            A[k * n : (k + 1) * n, (k - 1) * n : k * n] = L[k - 1]
            A[(k - 1) * n : k * n, k * n : (k + 1) * n] = L[k - 1].T
    A[K * n :, K * n :] = C
    return A


@pytest.mark.parametrize("transition", [False, True])
def test_rows_apply_pull_and_gram_match_the_dense_jacobian(transition):
    K, n, ng, m = 5, 4, 2, 3
    J, dense = random_rows(K, n, ng, m, transition, seed=int(transition))
    rng = np.random.default_rng(7)
    dz, dt = rng.normal(size=(K, n)), rng.normal(size=ng)
    R = K - 1 if transition else K
    v, w = rng.normal(size=(R, m)), rng.uniform(0.0, 2.0, size=(R, m))
    d = np.concatenate([dz.reshape(-1), dt])
    np.testing.assert_allclose(np.asarray(rows.apply(J, dz, dt)).reshape(-1), dense @ d, atol=1e-12)
    gz, gt = rows.pull(J, v, K)
    np.testing.assert_allclose(np.concatenate([np.asarray(gz).reshape(-1), gt]), dense.T @ v.reshape(-1), atol=1e-12)
    expected = dense.T @ np.diag(w.reshape(-1)) @ dense
    np.testing.assert_allclose(dense_blocks(rows.gram(J, w, K), K, n), expected, atol=1e-12)


@pytest.mark.parametrize("transition", [False, True])
def test_scaled_rows_are_the_jacobian_scaled_row_by_row(transition):
    """``rows.scaled`` keeps the factors beside the Jacobians: apply, pull and gram (dense and on
    row supports) equal those of diag(s₂ s₁) J, the factors of two calls multiplied."""
    K, n, ng, m = 5, 4, 2, 3
    J, dense = random_rows(K, n, ng, m, transition, seed=11)
    rng = np.random.default_rng(8)
    R = K - 1 if transition else K
    s1, s2 = rng.uniform(0.1, 3.0, size=(R, m)), rng.uniform(0.1, 3.0, size=(R, m))
    scaled = rows.scaled(rows.scaled(J, s1), s2)
    dense = np.diag((s1 * s2).reshape(-1)) @ dense
    dz, dt = rng.normal(size=(K, n)), rng.normal(size=ng)
    v, w = rng.normal(size=(R, m)), rng.uniform(0.0, 2.0, size=(R, m))
    np.testing.assert_allclose(np.asarray(rows.apply(scaled, dz, dt)).reshape(-1),
                               dense @ np.concatenate([dz.reshape(-1), dt]), atol=1e-12)
    gz, gt = rows.pull(scaled, v, K)
    np.testing.assert_allclose(np.concatenate([np.asarray(gz).reshape(-1), gt]), dense.T @ v.reshape(-1), atol=1e-12)
    expected = dense.T @ np.diag(w.reshape(-1)) @ dense
    np.testing.assert_allclose(dense_blocks(rows.gram(scaled, w, K), K, n), expected, atol=1e-12)
    every = (RowSupport(0, m, tuple(range(n)), tuple(range(n)) if transition else ()),)
    supported = rows.scaled(rows.scaled(rows.Rows(J.jz, J.jt, J.jn, every), s1), s2)
    np.testing.assert_allclose(dense_blocks(rows.gram(supported, w, K), K, n), expected, atol=1e-12)


@pytest.mark.parametrize("transition", [False, True])
def test_gram_on_row_supports_equals_the_dense_gram(transition):
    """Rows that are zero outside their declared columns: the run-by-run Gram blocks equal the
    dense ones (and a wrong partition of the rows is refused by name)."""
    K, n, ng = 5, 6, 1
    runs = (RowSupport(0, 2, (0, 3), (1, 2) if transition else ()), RowSupport(2, 2, (), ()),
            RowSupport(2, 5, (1, 4, 5), (0,) if transition else ()))
    J, _ = random_rows(K, n, ng, 5, transition, seed=3)
    mask_now, mask_next = np.zeros((5, n)), np.zeros((5, n))
    for run in runs:
        mask_now[run.start:run.stop, list(run.now)] = 1.0
        mask_next[run.start:run.stop, list(run.next)] = 1.0
    dense = rows.Rows(J.jz * mask_now, J.jt, None if J.jn is None else J.jn * mask_next)
    group = "transition_equality" if transition else "path_equality"
    blocks = types.SimpleNamespace(**{group + "_z": dense.jz, group + "_theta": dense.jt, group + "_znext": dense.jn})
    sparse = rows.group_rows(blocks, group, runs)
    assert sparse.supports == runs
    w = np.random.default_rng(4).uniform(0.0, 2.0, size=(K - 1 if transition else K, 5))
    for ours, expected in zip(rows.gram(sparse, w, K), rows.gram(dense, w, K), strict=True):
        np.testing.assert_allclose(ours, expected, atol=1e-12)
    with pytest.raises(ValueError, match=f"row supports of {group} must cover its 5 rows"):
        rows.group_rows(blocks, group, runs[:2])  # rows 2:5 left out


@pytest.mark.parametrize("supported", [False, True])
def test_grams_add_every_group_into_the_given_blocks(supported):
    """``grams(groups, weights, K, into=blocks)`` is ``blocks`` plus each group's ``gram``, with
    and without row supports, path and transition groups mixed."""
    K, n, ng, m = 5, 6, 1, 5
    runs = lambda transition: (RowSupport(0, 2, tuple(range(n)), tuple(range(n)) if transition else ()),  # noqa: E731
                               RowSupport(2, m, tuple(range(n)), tuple(range(n)) if transition else ()))
    groups = [random_rows(K, n, ng, m, transition, seed=10 + transition)[0] for transition in (False, True)]
    if supported:
        groups = [rows.Rows(g.jz, g.jt, g.jn, runs(g.jn is not None)) for g in groups]
    rng = np.random.default_rng(11)
    weights = [rng.uniform(0.0, 2.0, size=(K, m)), rng.uniform(0.0, 2.0, size=(K - 1, m))]
    into = (rng.normal(size=(K, n, n)), rng.normal(size=(K - 1, n, n)), rng.normal(size=(K, n, ng)),
            rng.normal(size=(ng, ng)))
    expected = rows.add(into, *(rows.gram(g, w, K) for g, w in zip(groups, weights)))
    for ours, want in zip(rows.grams(groups, weights, K, into=into), expected):
        np.testing.assert_allclose(ours, want, atol=1e-12)
    for ours, want in zip(rows.grams(groups, weights, K), rows.add(*(rows.gram(g, w, K) for g, w in zip(groups, weights)))):
        np.testing.assert_allclose(ours, want, atol=1e-12)


def test_group_rows_refuses_supports_that_do_not_partition_the_rows():
    blocks = types.SimpleNamespace(path_equality_z=np.zeros((3, 4, 5)), path_equality_theta=np.zeros((3, 4, 1)))
    with pytest.raises(ValueError, match="cover its 4 rows"):
        rows.group_rows(blocks, "path_equality", (RowSupport(0, 2, (0,)), RowSupport(3, 4, (1,))))
    with pytest.raises(ValueError, match="column outside"):
        rows.group_rows(blocks, "path_equality", (RowSupport(0, 4, (5,)),))
    with pytest.raises(ValueError, match="next knot"):
        rows.group_rows(blocks, "path_equality", (RowSupport(0, 4, (0,), (1,)),))
