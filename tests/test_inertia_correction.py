"""The inertia correction (``newton.factor`` with ``newton.next_regularisation``, IPOPT's rule
but for the decrease, Wächter & Biegler 2006, section 3.1) on a bordered block-tridiagonal
matrix whose smallest eigenvalue is −1/2: δ_w climbs its rungs until A + δ_w I factors, which
takes several attempts, and the factor it keeps is that of A + δ_w I."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import linalg, newton
from test_linalg import random_system

K, N, M = 9, 4, 2


def _indefinite():
    """(A, D, L, B, C) with λ_min(A) = −1/2: a random SPD system shifted down."""
    A, D, L, B, C = random_system(K, N, M, seed=3)
    shift = np.linalg.eigvalsh(A).min() + 0.5
    return A - shift * np.eye(K * N + M), D - shift * np.eye(N), L, B, C - shift * np.eye(M)


def _correct(last, correct=True, ceiling=1e40):
    _, D, L, B, C = _indefinite()
    blocks = tuple(jnp.asarray(a) for a in (D, L, B, C))
    return newton.factor(lambda delta: blocks, lambda delta: (jnp.full((K, N), delta), jnp.full((M,), delta)),
                         jnp.asarray(0.0), lambda delta: newton.next_regularisation(delta, jnp.asarray(last), 1e-3),
                         jnp.asarray(correct), ceiling, K)


@pytest.mark.parametrize("last, rungs", [(0.0, (0.0, 1e-4, 1e-2, 1.0)),  # none needed yet: 1e-4, then ×100
                                         (0.5, (0.0, 5e-4, 4e-3, 3.2e-2, 0.256, 2.048))])  # last × 1e-3, then ×8
def test_the_correction_climbs_until_the_matrix_factors(last, rungs):
    A = _indefinite()[0]
    delta, chol, ok, work = _correct(last)
    assert bool(ok) and float(delta) == pytest.approx(rungs[-1], rel=1e-12)
    # Every rung below −λ_min = 1/2 failed, each after the blocks up to its first failing one.
    assert K < int(work) <= len(rungs) * K
    r = np.random.default_rng(0).normal(size=K * N + M)
    x, y = linalg.solve(chol, r[: K * N].reshape(K, N), r[K * N :])
    expected = np.linalg.solve(A + float(delta) * np.eye(K * N + M), r)
    assert np.allclose(np.concatenate([np.asarray(x).ravel(), y]), expected, rtol=1e-10, atol=1e-10)


def test_without_correction_one_attempt_reports_the_failure():
    delta, chol, ok, work = _correct(0.0, correct=False)
    assert not bool(ok) and not bool(chol.ok) and float(delta) == 0.0 and int(work) <= K


def test_the_ceiling_stops_the_climb_unfactored():
    delta, _, ok, _ = _correct(0.0, ceiling=1e-3)
    assert not bool(ok) and float(delta) == pytest.approx(1e-2)  # 0, 1e-4, then 1e-2 ≥ the ceiling
