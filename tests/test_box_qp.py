"""The box-constrained QP of the inner Newton step against its optimality conditions."""

import jax
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import box_qp
from test_linalg import _random_system


@pytest.mark.parametrize("seed", range(4))
def test_box_qp_satisfies_the_kkt_conditions(seed):
    """At the returned d: inside the box; zero gradient on free entries; the gradient points
    outwards on entries at a bound (a convex QP: these conditions are optimality)."""
    K, n, m = 6, 5, 1
    A, D, L, B, C = _random_system(K, n, m, seed=seed)
    rng = np.random.default_rng(seed)
    g = (5 * rng.normal(size=(K, n)), 5 * rng.normal(size=m))
    lo = (-rng.uniform(0.0, 1.0, size=(K, n)), np.full(m, -np.inf))
    hi = (rng.uniform(0.0, 1.0, size=(K, n)), np.full(m, np.inf))
    lo[0][0, :2] = hi[0][0, :2] = 0.0  # fixed entries
    (dz, dt), ok = jax.jit(box_qp.solve, static_argnums=4)((D, L, B, C), g, lo, hi, 50)
    assert bool(ok)
    d = np.concatenate([np.asarray(dz).reshape(-1), dt])
    low, high = np.concatenate([lo[0].reshape(-1), lo[1]]), np.concatenate([hi[0].reshape(-1), hi[1]])
    grad = np.concatenate([g[0].reshape(-1), g[1]]) + A @ d
    assert np.all(d >= low) and np.all(d <= high)
    at_low, at_high = d <= low + 1e-12, d >= high - 1e-12
    free = ~(at_low | at_high)
    assert np.abs(grad[free]).max(initial=0.0) <= 1e-8
    assert np.all(grad[at_low & ~at_high] >= -1e-8) and np.all(grad[at_high & ~at_low] <= 1e-8)
    assert (at_low | at_high).sum() > 2  # the bounds matter in these instances


def test_box_qp_without_active_bounds_is_the_newton_step():
    K, n, m = 5, 3, 2
    A, D, L, B, C = _random_system(K, n, m, seed=9)
    rng = np.random.default_rng(2)
    g = (rng.normal(size=(K, n)), rng.normal(size=m))
    wide = (np.full((K, n), -1e6), np.full(m, -1e6)), (np.full((K, n), 1e6), np.full(m, 1e6))
    (dz, dt), ok = box_qp.solve((D, L, B, C), g, *wide, 5)
    expected = np.linalg.solve(A, -np.concatenate([g[0].reshape(-1), g[1]]))
    assert bool(ok)
    assert np.abs(np.concatenate([np.asarray(dz).reshape(-1), dt]) - expected).max() <= 1e-10


@pytest.mark.parametrize("seed", range(3))
def test_penalty_rows_model_satisfies_its_optimality_conditions(seed):
    """With penalised rows ρ/2 dist(a + J d, [l, u])² (path and transition), the returned d is
    optimal for the convex piecewise-quadratic model over the box: zero gradient on free
    entries, outward gradient at bounds; and some rows end active, some inactive."""
    from test_rows import random_rows

    K, n, m = 6, 5, 1
    A, D, L, B, C = _random_system(K, n, m, seed=seed)
    rng = np.random.default_rng(seed + 10)
    g = (3 * rng.normal(size=(K, n)), 3 * rng.normal(size=m))
    lo = (-rng.uniform(0.2, 1.0, size=(K, n)), np.full(m, -np.inf))
    hi = (rng.uniform(0.2, 1.0, size=(K, n)), np.full(m, np.inf))
    penalties, dense = [], []
    for transition in (False, True):
        J, Jd = random_rows(K, n, m, 2, transition, seed=seed + 20 + transition)
        R = K - 1 if transition else K
        shifted = rng.normal(size=(R, 2))
        lower, upper = np.array([-0.5, -np.inf]), np.array([0.5, 0.2])
        penalty = rng.uniform(1.0, 20.0, size=(R, 2))
        penalties.append(box_qp.PenaltyRows(J, shifted, penalty, lower, upper))
        dense.append((Jd, shifted.reshape(-1), penalty.reshape(-1), np.tile(lower, R), np.tile(upper, R)))
    (dz, dt), ok = box_qp.solve((D, L, B, C), g, lo, hi, 50, tuple(penalties))
    assert bool(ok)
    d = np.concatenate([np.asarray(dz).reshape(-1), dt])
    grad = np.concatenate([g[0].reshape(-1), g[1]]) + A @ d
    active = []
    for Jd, a, rho, lower, upper in dense:
        r = a + Jd @ d
        grad += Jd.T @ (rho * (r - np.clip(r, lower, upper)))
        active.append((r < lower) | (r > upper))
    active = np.concatenate(active)
    low, high = np.concatenate([lo[0].reshape(-1), lo[1]]), np.concatenate([hi[0].reshape(-1), hi[1]])
    assert np.all(d >= low) and np.all(d <= high)
    at_low, at_high = d <= low + 1e-12, d >= high - 1e-12
    free = ~(at_low | at_high)
    assert np.abs(grad[free]).max(initial=0.0) <= 1e-8
    assert np.all(grad[at_low] >= -1e-8) and np.all(grad[at_high] <= 1e-8)
    assert 0 < active.sum() < active.size
