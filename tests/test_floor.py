"""``tools/floor.py``'s random Newton-matrix structure: symmetric positive definite,
coupled only in the columns it names, and factored and solved by ``linalg`` as a dense solve
does; its FLOP count adds up the two chains' kernels."""

import importlib.util
import pathlib
import sys

import jax.numpy as jnp
import numpy as np

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import linalg

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # floor.py imports benchmarks/machine.py
spec = importlib.util.spec_from_file_location("floor", ROOT / "tools" / "floor.py")
floor = importlib.util.module_from_spec(spec)
spec.loader.exec_module(floor)


def _dense(D, L, B, C):
    K, n, m = D.shape[0], D.shape[1], C.shape[0]
    A = np.zeros((K * n + m, K * n + m))
    for k in range(K):
        A[k * n:(k + 1) * n, k * n:(k + 1) * n] = D[k]
        A[k * n:(k + 1) * n, K * n:] = B[k]
        A[K * n:, k * n:(k + 1) * n] = B[k].T
    for k in range(K - 1):
        A[(k + 1) * n:(k + 2) * n, k * n:(k + 1) * n] = L[k]
        A[k * n:(k + 1) * n, (k + 1) * n:(k + 2) * n] = L[k].T
    A[K * n:, K * n:] = C
    return A


def test_random_system_is_spd_coupled_in_its_columns_and_solved_as_dense():
    K, n, m = 6, 7, 1
    coupled = np.array([1, 2, 5])
    D, L, B, C = floor.random_system(K, n, coupled, m)
    assert not np.any(np.delete(L, coupled, axis=2))
    A = _dense(D, L, B, C)
    assert np.allclose(A, A.T) and np.linalg.eigvalsh(A).min() > 0
    chol = linalg.factor(*(jnp.asarray(a) for a in (D, L, B, C)), coupled=tuple(coupled))
    assert bool(chol.ok)
    rng = np.random.default_rng(3)
    r, s = rng.standard_normal((K, n)), rng.standard_normal(m)
    x, y = linalg.solve(chol, r, s)
    expected = np.linalg.solve(A, np.concatenate([r.ravel(), s]))
    assert np.allclose(np.concatenate([np.asarray(x).ravel(), np.asarray(y)]), expected, rtol=1e-10, atol=1e-12)


def test_flop_count_adds_the_chains_kernels():
    # K = 3: one forward block, one backward block, the middle; n = 2, s = 1, no border.
    cholesky = 3 * 2**3 / 3
    forward = 1 * 1 * 2 + 2 * 2 * 2 * 1  # triangular solve s² n, update 2 n² s
    backward = 2 * 2 * 1 + 2 * 1 * 1 * 2  # triangular solve n² s, update 2 s² n
    assert floor.factorisation_flops(3, 2, 1) == cholesky + forward + backward
    assert floor.factorisation_flops(3, 2, 1, m=1) > floor.factorisation_flops(3, 2, 1)
